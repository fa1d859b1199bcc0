"""Terminal output shared by the commands: a rich console, progress bars and tables."""

from __future__ import annotations

import contextlib
import sys
from typing import Callable, Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

console = Console(stderr=False, highlight=False)


@contextlib.contextmanager
def progress_bar(description: str, total: int) -> Iterator[Callable[[int], None]]:
    """A progress bar; yields ``update(completed)``. Silent when stdout is not a terminal... except at the end."""
    prog = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
        disable=not sys.stdout.isatty(),
    )
    with prog:
        task = prog.add_task(description, total=total)
        yield lambda done: prog.update(task, completed=done)
        prog.update(task, completed=total)


def summary_table(title: str, rows: list[tuple[str, str]]) -> Table:
    """A two-column table (quantity, value)."""
    t = Table(title=title, show_header=True, header_style="bold")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    for k, v in rows:
        t.add_row(k, v)
    return t


STAGE_TEXT = {
    "read": "reading the scene", "voxelize": "voxelizing", "triangles": "voxelizing the mesh triangles",
    "floaters": "floater filter: what it leaves uncovered",
    "cover": "cover: clusters, set cover, merging", "budget": "budget: reduce, quantize, measure candidates",
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
            else:
                self._cm = console.status(text)
            self._update = self._cm.__enter__()
        if total > 1 and self._update is not None:
            self._update(int(done))

    def __enter__(self) -> "StageProgress":
        return self

    def __exit__(self, *exc) -> None:
        self._close()
