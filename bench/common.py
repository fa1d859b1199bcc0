"""Helpers shared by the benchmarks: paths, result tables and JSON output."""

from __future__ import annotations

import json
import os
import platform
import resource
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = Path(os.environ.get("POLYCC_SHARED_SCENES", REPO.parent / "shared" / "scenes"))  # as polycc.testing.files
RESULTS = REPO / "bench" / "results"
CACHE = REPO / "build" / "bench-cache"


def peak_rss_mb(children: bool = False) -> float:
    """Peak resident set size in MiB of this process (or of its finished children)."""
    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return resource.getrusage(who).ru_maxrss / 1024.0


def print_table(title: str, header: list[str], rows: list[list]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=title)
    for h in header:
        t.add_column(h, justify="right")
    for r in rows:
        t.add_row(*[f"{v:,.3g}" if isinstance(v, float) else (f"{v:,}" if isinstance(v, int) else str(v)) for v in r])
    Console(width=160).print(t)


def write_json(name: str, payload: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    payload = {"machine": {"python": sys.version.split()[0], "platform": platform.platform()}, **payload}
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2))
    print(f"wrote {path}")
    return path
