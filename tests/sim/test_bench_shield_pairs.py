"""bench/bench_shield.py's paired jerk comparison, by the flights' outcomes (docs/barrier.md section 8): the
classes partition the pairs and each class's figures are those of its pairs alone."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("scipy")


@pytest.fixture(scope="module")
def bench_shield():
    path = Path(__file__).resolve().parents[2] / "bench" / "bench_shield.py"
    spec = importlib.util.spec_from_file_location("bench_shield_under_test", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _row(mode, ids, jerk, outcome):
    return {"dynamics": "firmware", "speed": 0.5, "mode": mode, "pair_ids": ids, "flight_jerk_rms": jerk,
            "flight_outcome": outcome}


def test_outcome_classes_partition_the_pairs(bench_shield):
    rng = np.random.default_rng(3)
    ids = list(range(40))
    app_j, sh_j = rng.uniform(1, 5, 40), rng.uniform(1, 5, 40)
    app_o = list(rng.choice(["goal", "stuck", "timeout"], 40))
    sh_o = list(rng.choice(["goal", "stuck"], 40))
    rows = [_row("app", ids, list(app_j), app_o), _row("app_shield", ids[5:] + [99], list(sh_j[5:]) + [1.0],
                                                           sh_o[5:] + ["goal"])]
    out = {r["outcomes"]: r for r in bench_shield.paired_jerk(rows, by_outcome=True)}
    assert set(out) == set(bench_shield.OUTCOME_CLASSES)
    parts = [k for k in out if k != "all"]
    assert sum(out[k]["pairs"] for k in parts) == out["all"]["pairs"] == 35  # common pairs only
    both = [k for k in range(5, 40) if app_o[k] == "goal" and sh_o[k] == "goal"]
    r = sh_j[both] / app_j[both]
    assert out["both reach the goal"]["pairs"] == len(both)
    assert out["both reach the goal"]["smoother"] == int((r < 1).sum())
    assert np.isclose(out["both reach the goal"]["geomean_ratio"], np.exp(np.mean(np.log(r))))
    stalled = [k for k in range(5, 40) if app_o[k] == "goal" and sh_o[k] != "goal"]
    assert out["only the base reaches it"]["pairs"] == len(stalled)
    # without the split: the pooled row only, as before
    assert [r["outcomes"] for r in bench_shield.paired_jerk(rows)] == ["all"]


def test_rows_without_outcomes_give_the_pooled_row_only(bench_shield):
    rows = [_row("app", [0, 1, 2], [1.0, 2.0, 3.0], None), _row("app_shield", [0, 1, 2], [2.0, 2.0, 1.5], None)]
    for r in rows:
        del r["flight_outcome"]
    out = bench_shield.paired_jerk(rows, by_outcome=True)
    assert [r["outcomes"] for r in out] == ["all"] and out[0]["smoother"] == 1
