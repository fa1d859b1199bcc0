"""Print what failed in a pytest run, short, from its JUnit XML (``make test`` calls it when pytest fails).

Why: CI keeps only the tail of the log. A run that ends in an xdist INTERNALERROR prints the internal
traceback last, and the failures it had already seen scroll out of that tail (2026-12-07: "2 failed" with
no names). This runs after pytest and prints, last, each failed or errored test with its duration (a test
near pytest-timeout's limit shows as such) and the first lines of its message, then the slowest tests.

Usage: ``python tools/failure_summary.py REPORT.xml [PYTEST_EXIT_CODE]``.
"""

from __future__ import annotations

import sys
import xml.etree.ElementTree as ET
from pathlib import Path

LINES = 12  # of each failure's text (its first and last six)
SLOWEST = 5


def _nodeid(case: ET.Element) -> str:
    cls, name = case.get("classname", ""), case.get("name", "")
    parts = cls.split(".")
    # classname is the module path with dots (tests.sim.test_x) and maybe a class; rebuild a pytest node id
    for i in range(len(parts), 0, -1):
        if parts[i - 1].startswith("test_"):
            path = "/".join(parts[:i]) + ".py"
            return "::".join([path, *parts[i:], name])
    return f"{cls}::{name}"


def summarise(report: Path, exit_code: int | None = None) -> str:
    """The summary text of the JUnit XML ``report`` (str, ends with a newline)."""
    if not report.is_file():
        return f"test summary: no report at {report} (pytest stopped before writing it)\n"
    root = ET.parse(report).getroot()
    cases = list(root.iter("testcase"))
    counts = {"passed": 0, "failed": 0, "error": 0, "skipped": 0}
    bad = []
    for c in cases:
        kind = next((k for k in ("failure", "error") if c.find(k) is not None), None)
        if kind is None:
            counts["skipped" if c.find("skipped") is not None else "passed"] += 1
            continue
        counts["failed" if kind == "failure" else "error"] += 1
        el = c.find(kind)
        text = "\n".join(filter(None, [el.get("message", ""), el.text or ""]))
        bad.append((_nodeid(c), kind, float(c.get("time", 0.0)), text))
    out = ["", "=" * 30 + " test summary (tools/failure_summary.py) " + "=" * 30]
    if exit_code == 3:
        out.append("pytest ended in an INTERNALERROR (exit 3): tests after it did not run; see the traceback above")
    for node, kind, t, text in bad:
        out.append(f"{kind.upper()} {node} ({t:.1f} s)")
        lines = text.strip().splitlines()
        if len(lines) > LINES:  # the head names the failure, the tail holds where it was raised
            lines = lines[:LINES // 2] + [f"... {len(lines) - LINES} lines ..."] + lines[-(LINES // 2):]
        out.extend("    " + ln for ln in lines)
    slow = sorted(cases, key=lambda c: -float(c.get("time", 0.0)))[:SLOWEST]
    out.append("slowest: " + "; ".join(f"{_nodeid(c)} {float(c.get('time', 0.0)):.0f} s" for c in slow))
    out.append(", ".join(f"{v} {k}" for k, v in counts.items()) + f" (of {len(cases)} with a result)")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args:
        print(__doc__, file=sys.stderr)
        return 2
    sys.stdout.write(summarise(Path(args[0]), int(args[1]) if len(args) > 1 else None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
