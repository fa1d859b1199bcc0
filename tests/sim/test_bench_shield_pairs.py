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


def test_the_flown_figure_leaves_out_the_hand_over(bench_shield):
    """A flight's jerk after its first 30 ms (the hand-over from the high-level commander, the largest jerk of most
    flights in both modes) is compared pair by pair on its own: here the two modes differ only in the hand-over
    (the shield's 4x smaller), and after it the shield is 1.5x rougher: the whole-flight figure says smoother,
    the flown one rougher."""
    import sys

    sys.path.insert(0, str(Path(bench_shield.__file__).parent))
    from flight_store import decode, encode

    rng = np.random.default_rng(5)

    def rec(first, rest_scale, k):
        j = np.r_[np.full(3, first), rest_scale * rng.standard_normal(400)]
        return k, {"jerk": encode(j), "gap": encode(np.zeros(0)), "jerk_rms": float(np.sqrt(np.mean(j ** 2))),
                   "success": True, "shield": None, "collisions": 0, "min_clearance_m": 0.1, "time_s": 4.0,
                   "outcome": "goal", "landed": True, "sitl_reruns": 0, "rtf": 0.8}

    class Cell:
        class path:
            name = "cell.json"

    app = [rec(200.0, 2.0, k) for k in range(10)]
    sh = [rec(50.0, 3.0, k) for k in range(10)]
    rows = [bench_shield._firmware_row(0.5, m, recs, Cell, "0" * 16, 0)
            for m, recs in (("app", app), ("app_shield", sh))]
    j0 = decode(app[0][1]["jerk"])
    assert rows[0]["flight_jerk_rms_flown"][0] == pytest.approx(np.sqrt(np.mean(j0[3:] ** 2)))
    whole = bench_shield.paired_jerk(rows)[0]
    flown = bench_shield.paired_jerk(rows, key="flight_jerk_rms_flown")[0]
    assert whole["figure"] == "flight_jerk_rms" and whole["median_ratio"] < 1 and whole["smoother"] == 10
    assert flown["figure"] == "flight_jerk_rms_flown" and 1.3 < flown["median_ratio"] < 1.7 and flown["smoother"] == 0
