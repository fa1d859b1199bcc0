"""Terminal output shared by the commands: a rich console, progress bars and tables.

On a terminal, long steps show a bar with ETA; when stdout is piped or redirected they print plain
progress lines instead (at most one every ``PIPE_EVERY_S`` seconds, plus the first and the last), so a
log shows that work goes on. Tables fit 80 columns (their text wraps)."""

from __future__ import annotations

import contextlib
import sys
import time
from typing import Callable, Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

console = Console(stderr=False, highlight=False)
err_console = Console(stderr=True, highlight=False)
PIPE_EVERY_S = 5.0


def warn(line: str) -> None:
    """A one-line warning on stderr (before heavy work: non-metric extent, large voxelization)."""
    err_console.print(f"[yellow]warning:[/yellow] {line}", soft_wrap=True)


def _tty() -> bool:
    return sys.stdout.isatty()


class _PipeProgress:
    """Progress lines for a piped stdout: 'description: done/total (pct), elapsed, ETA'."""

    def __init__(self, description: str, total: int):
        self.description, self.total = description, max(int(total), 1)
        self.t0 = time.monotonic()
        self.last = -1e9
        self.done = 0

    def line(self, done: int, final: bool = False) -> None:
        now = time.monotonic()
        self.done = done
        if not final and now - self.last < PIPE_EVERY_S:
            return
        self.last = now
        el = now - self.t0
        frac = min(done / self.total, 1.0)
        eta = f", ETA {el * (1 - frac) / frac:.0f} s" if 0 < frac < 1 else ""
        print(f"{self.description}: {done:,}/{self.total:,} ({100 * frac:.0f} %), {el:.0f} s{eta}", flush=True)


@contextlib.contextmanager
def progress_bar(description: str, total: int) -> Iterator[Callable[[int], None]]:
    """A progress bar with ETA on a terminal; progress lines when stdout is piped. Yields ``update(completed)``."""
    if not _tty():
        pp = _PipeProgress(description, total)
        pp.line(0)
        yield pp.line
        pp.line(total, final=True)
        return
    prog = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    )
    with prog:
        task = prog.add_task(description, total=total)
        yield lambda done: prog.update(task, completed=done)
        prog.update(task, completed=total)


def summary_table(title: str, rows: list[tuple[str, str]]) -> Table:
    """A two-column table (quantity, value)."""
    t = Table(title=title, show_header=True, header_style="bold")
    t.add_column("quantity", ratio=3, overflow="fold")
    t.add_column("value", justify="right", ratio=2, overflow="fold")
    for k, v in rows:
        t.add_row(k, v)
    return t


STAGE_TEXT = {
    "read": "reading the scene", "voxelize": "voxelizing", "triangles": "voxelizing the mesh triangles",
    "floaters": "floater filter: what it leaves uncovered",
    "cover": "cover: clusters, set cover, merging", "budget": "budget: reduce, quantize, measure candidates",
    "drop costs": "budget: the volume each half-plane's drop adds (every polytope)",
    "pops": "budget: the reduction's next drops, every polytope",
    "write": "writing polytopes.h, manifest.json, report.png",
    "certificate": "(a) certificate, every level", "levels": "(a)(b)(c) direct checks",
}


class StageProgress:
    """A pipeline ``progress(stage, done, total)`` callback shown on the console: a bar for stages
    that report a total, a status line for the others. Use as a context manager."""

    def __init__(self):
        self._stage = None
        self._cm = None
        self._update = None

    def _close(self):
        if self._cm is not None:
            self._cm.__exit__(None, None, None)
        self._cm, self._update, self._stage = None, None, None

    def __call__(self, stage: str, done: float, total: float) -> None:
        if stage != self._stage:
            self._close()
            self._stage = stage
            text = STAGE_TEXT.get(stage, stage)
            if total > 1:
                self._cm = progress_bar(text, int(total))
            elif _tty():
                self._cm = console.status(text)
            else:
                print(f"{text}...", flush=True)
                self._cm = contextlib.nullcontext(None)
            self._update = self._cm.__enter__()
        if total > 1 and self._update is not None:
            self._update(int(done))

    def __enter__(self) -> "StageProgress":
        return self

    def __exit__(self, *exc) -> None:
        self._close()
