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
