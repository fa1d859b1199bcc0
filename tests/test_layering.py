"""Imports run one way: the pipeline never imports sim, ground or verify; verify imports nothing of
the pipeline; nothing imports tests/ or bench/.  Read with ast (imports inside functions count)."""

from __future__ import annotations

import ast
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "polycc"

# A unit may import units of strictly lower rank (and itself). The pipeline is ranks 0..7.
RANK = {
    "errors": 0, "version": 0,
    "geometry": 1, "link": 1, "report": 1, "verify": 1, "resources": 1, "parallel": 1,
    "firmware_trees": 2,  # firmware tarball/tree extraction and validation, shared by sim.firmware and ground.flash
    "scene": 2, "cbuild": 2,
    "native": 2.5,  # host-only C geometry kernels (cffi): the cover's and the budget's hot loops
    "occupancy": 3, "demo": 3,
    "cover": 4, "onboard": 4,
    "budget": 5,
    "codegen": 6,
    "pipeline": 7,
    "plan": 7.5,  # planner on the certified free space: may import onboard, geometry, budget; the pipeline does not
    "sim": 8, "ground": 8, "view": 8,
    "swarm": 8.5,  # N app instances, coverage controllers: imports sim and plan
    "testing": 9,
    "cli": 10, "polycc": 10, "__main__": 11,
}
PIPELINE = {u for u, r in RANK.items() if r <= 7} - {"link", "verify"}
STDLIB = set(sys.stdlib_module_names)


def _unit(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else "polycc"


def _imports(path: Path):
    mod = ".".join(path.relative_to(ROOT).with_suffix("").parts)
    pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            if base == "polycc":  # from polycc import x: x is a unit
                for a in node.names:
                    yield f"polycc.{a.name}", node.lineno
            else:
                yield base, node.lineno


def _sources():
    return sorted(p for p in PKG.rglob("*.py"))


def test_every_unit_has_a_rank():
    units = {_unit(".".join(p.relative_to(ROOT).with_suffix("").parts).replace(".__init__", "")) for p in _sources()}
    assert units <= set(RANK), f"add these units to RANK: {sorted(units - set(RANK))}"


def test_imports_run_one_way():
    bad = []
    for path in _sources():
        mod = ".".join(path.relative_to(ROOT).with_suffix("").parts).replace(".__init__", "")
        src = _unit(mod)
        for name, line in _imports(path):
            top = name.split(".")[0]
            if top in ("tests", "bench", "tools", "conftest", "host_sim"):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
            if top != "polycc":
                continue
            dst = _unit(name)
            if dst != src and RANK.get(dst, 99) >= RANK[src]:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({src}, rank {RANK[src]}) imports {name} "
                           f"({dst}, rank {RANK.get(dst)})")
    assert not bad, "imports against the layering:\n" + "\n".join(bad)


def test_pipeline_never_imports_sim_ground_or_verify():
    for path in _sources():
        mod = ".".join(path.relative_to(ROOT).with_suffix("").parts).replace(".__init__", "")
        if _unit(mod) not in PIPELINE:
            continue
        for name, line in _imports(path):
            if name.startswith("polycc."):
                assert _unit(name) not in ("sim", "ground", "verify", "cli", "testing"), f"{path}:{line}: {name}"


def test_verify_imports_only_numpy_scipy_and_errors():
    """The checker shares no code with the pipeline it checks."""
    for path in sorted((PKG / "verify").rglob("*.py")):
        for name, line in _imports(path):
            top = name.split(".")[0]
            ok = top in ("numpy", "scipy", "__future__") or top in STDLIB or name in ("polycc.errors",) \
                or name.startswith("polycc.verify")
            assert ok, f"{path.relative_to(ROOT)}:{line} imports {name}"


def test_tests_do_not_import_each_other():
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for name, line in _imports(path):
            top = name.split(".")[0]
            assert top not in ("tests", "conftest", "bench") and not top.startswith("test_"), \
                f"{path.relative_to(ROOT)}:{line} imports {name}; shared helpers belong in polycc.testing"


def test_every_package_is_installed():
    """pyproject.toml lists the packages explicitly (so firmware_app/ can be mapped in): none missing."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in PKG.rglob("__init__.py")}
    assert found <= listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"


@pytest.mark.parametrize("name", ["load_scene", "voxelize", "build_cover", "build", "verify"])
def test_curated_api(name):
    import polycc

    fn = getattr(polycc, name)
    assert callable(fn) and fn.__doc__ and "Parameters" in fn.__doc__ and "Returns" in fn.__doc__
    assert name in polycc.__all__
