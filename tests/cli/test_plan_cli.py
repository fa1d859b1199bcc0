"""`polycc plan` and `polycc sim --plan` on a small build: table, plan.json, plan.png, the no-path
error (one line, exit 3) and flights along the plan."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polycc.cli import main
from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box
from polycc.scene.ellipsoids import Ellipsoids, quaternion_to_rotation

WALLS = [((0.0, -1.5, 0.0), (0.6, -0.28, 1.5)), ((0.0, 0.28, 0.0), (0.6, 1.5, 1.5))]
BOUNDS = "--bounds=-1.5,-1.8,0,2.2,1.8,1.5"
START, GOAL = "--start=-1,-0.9,0.7", "--goal=1.1,-0.9,0.7"


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """A build folder of two walls, with a scene file of splats on them (ground truth for sim)."""
    from polycc.scene.writers import write_gaussian_ply

    d = tmp_path_factory.mktemp("plan_cli")
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(lo, hi, size=(3000, 3)) for lo, hi in WALLS])
    n = len(pts)
    q = rng.normal(size=(n, 4))
    ell = Ellipsoids(pts, quaternion_to_rotation(q / np.linalg.norm(q, axis=1, keepdims=True)),
                     np.full((n, 3), 0.004), k=1.0, opacity=np.ones(n, np.float32),
                     colors=np.full((n, 3), 128, np.uint8))
    ply = d / "walls.ply"
    write_gaussian_ply(ply, ell)
    write_outputs(d, [axis_box(np.array(lo) - 0.02, np.array(hi) + 0.02) for lo, hi in WALLS],
                  {"kappa": 100.0, "scene": {"name": ply.name, "path": str(ply)}})
    return d, ply


def test_plan_command(build, tmp_path, capsys):
    d, _ = build
    rc = main(["plan", str(d), START, GOAL, BOUNDS, "--json", str(tmp_path / "p.json"),
               "--plot", str(tmp_path / "p.png")])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "summary:" in out and "waypoints" in out and "psi >=" in out
    plan = json.loads((tmp_path / "p.json").read_text())
    assert plan["format"] == "polycc-plan/1" and len(plan["waypoints"]) >= 3
    assert plan["waypoints"][0] == [-1.0, -0.9, 0.7] and plan["waypoints"][-1] == [1.1, -0.9, 0.7]
    assert min(plan["clearance"]["segment_psi_min_sampled_m"]) >= 0.0
    assert (tmp_path / "p.png").stat().st_size > 10_000
    assert main(["plan", str(d), START, GOAL, BOUNDS]) == 0  # defaults: DIR/plan.json, DIR/plan.png
    assert (d / "plan.json").is_file() and (d / "plan.png").is_file()


def test_plan_no_path_is_one_line(build, capsys):
    d, _ = build
    rc = main(["plan", str(d), START, "--goal=0.3,-1,0.7", BOUNDS])
    err = capsys.readouterr().err.strip()
    assert rc == 3 and len(err.splitlines()) == 1 and "goal_in_obstacle" in err and "Traceback" not in err
    assert main(["plan", str(d), START, "--goal=9,0,0.7", BOUNDS]) == 3
    assert "outside the map" in capsys.readouterr().err
    assert main(["plan", str(d), START, GOAL, "--margin", "-1"]) == 2  # range-checked option


def test_plan_help_has_units(capsys):
    assert main(["plan", "--help"]) == 0
    out = capsys.readouterr().out
    for opt in ("--radius", "--margin", "--grid", "--bounds", "--start", "--goal"):
        assert opt in out
    assert "radius, m" in out and "spacing, m" in out
    assert main(["sim", "--help"]) == 0 and "--plan" in capsys.readouterr().out


def test_sim_with_plan(build, tmp_path, capsys):
    d, ply = build
    rc = main(["sim", str(d), "--scene", str(ply), START, GOAL, BOUNDS, "--vmax", "1", "--plan",
               "--plot", str(tmp_path / "t.png")])
    out = capsys.readouterr().out
    assert rc == 0 and "success 1/1" in out and "collisions: 0" in out, out
    summary = json.loads((d / "sim.json").read_text())
    assert summary["trials"][0]["plan"]["waypoints_reached"] == len(summary["trials"][0]["plan"]["waypoints"]) - 1
    rc = main(["sim", str(d), "--scene", str(ply), START, GOAL, BOUNDS, "--vmax", "1", "--t-max", "15",
               "--plot", str(tmp_path / "t.png")])
    assert rc == 0 and "success 0/1" in capsys.readouterr().out  # the same flight without a plan gets stuck
    rc = main(["sim", str(d), "--scene", str(ply), "--random-pairs", "3", "--min-distance", "1.0", "--rate-hz", "100",
               "--plan", BOUNDS, "--plot", str(tmp_path / "r.png")])
    out = capsys.readouterr().out
    assert rc == 0 and "planned:" in out and "collisions: 0" in out
    assert main(["sim", str(d), "--scene", str(ply), START, "--goal=0.3,-1,0.7", BOUNDS, "--plan"]) == 3
