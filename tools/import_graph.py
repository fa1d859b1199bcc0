#!/usr/bin/env python3
"""Print the import graph of the polycc sources between top-level units, and any cycle.

Usage: python tools/import_graph.py [--modules | --packages]   (run from the project root)

A unit is a sub-package of ``polycc`` (``polycc/cover/...`` -> ``cover``), a top-level module of
``polycc`` (``polycc/pipeline.py`` -> ``pipeline``), or another top-level package of the
checkout (``host_sim``). With ``--modules`` every module is its own node, with ``--packages``
every top-level package (``polycc``, ``host_sim``). Imports are read with
``ast`` (also those inside functions); nothing is imported or run.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("polycc", "host_sim")


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    mod = module_name(path)
    pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = pkg.split(".")
                up = up[: len(up) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


def unit(name: str, modules: bool | str) -> str | None:
    parts = name.split(".")
    if parts[0] not in PACKAGES:
        return None
    if modules == "packages":
        return parts[0]
    if modules:
        return name
    if parts[0] == "polycc":
        return parts[1] if len(parts) > 1 else "polycc"
    return parts[0]


def graph(modules: bool | str = False) -> dict[str, set[str]]:
    known = set()
    files = [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py")) if (ROOT / pkg).is_dir()]
    for f in files:
        known.add(module_name(f))
    edges: dict[str, set[str]] = defaultdict(set)
    for f in files:
        src = unit(module_name(f), modules)
        edges.setdefault(src, set())
        for imp in imports(f):
            # keep the longest known module prefix (from polycc.x import name -> polycc.x)
            while imp and imp not in known:
                imp = imp.rpartition(".")[0]
            dst = unit(imp, modules) if imp else None
            if dst and dst != src:
                edges[src].add(dst)
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modules", action="store_true", help="one node per module instead of per unit")
    ap.add_argument("--packages", action="store_true", help="one node per top-level package")
    args = ap.parse_args()
    edges = graph("packages" if args.packages else args.modules)
    for src in sorted(edges):
        print(f"{src} -> {', '.join(sorted(edges[src])) or '(nothing)'}")
    cyc = cycles(edges)
    print(f"\n{sum(len(v) for v in edges.values())} edges between {len(edges)} units; "
          f"{len(cyc)} cycle(s){': ' if cyc else ''}" + "; ".join(" <-> ".join(c) for c in cyc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
