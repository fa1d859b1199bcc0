"""report.png stays readable with hundreds of polytopes (depth-ordered fills), trajectories.png has a legend."""

from __future__ import annotations

from types import SimpleNamespace

import matplotlib.image
import numpy as np

from polycc.report.flights import plot_trajectories
from polycc.report.plots import write_report


def _box(lo, hi):
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], float)


def test_report_top_view_shows_the_highest_polytope_on_top(tmp_path):
    """800 polytopes: where a tall box stands over low ones, the top view shows the tall box's colour (the
    top of the colour scale), not whichever polytope happened to be drawn last."""
    rng = np.random.default_rng(0)
    polys = []
    for _ in range(799):
        c = rng.uniform([-3, -3, 0], [3, 3, 0.5])
        polys.append(_box(c - 0.2, c + 0.2))
    polys.insert(300, _box([-0.5, -0.5, 0.0], [0.5, 0.5, 2.0]))  # the tallest, drawn mid-list
    out = write_report(tmp_path / "report.png", rng.uniform(-3, 3, (5000, 3)), polys, [(100, 1.2, 0.01),
                                                                                       (800, 1.01, 0.01)],
                       (800, 1.01), "800 polytopes")
    img = matplotlib.image.imread(out)[..., :3]
    h, w = img.shape[:2]
    # the top view is the upper-left panel; find its axes centre by the tall box's colour (viridis top = yellow)
    top = img[: h // 2, : w // 2]
    yellow = (top[..., 0] > 0.8) & (top[..., 1] > 0.8) & (top[..., 2] < 0.35)
    assert yellow.sum() > 500, "the tallest polytope is hidden under lower ones in the top view"
    ys, xs = np.nonzero(yellow)
    assert (ys.max() - ys.min()) < h // 6 and (xs.max() - xs.min()) < w // 6  # one compact square


def test_trajectories_png_has_a_legend(tmp_path):
    trial = SimpleNamespace(positions=np.linspace([0, 0, 1], [1, 1, 1], 20), start=np.array([0, 0, 1.0]),
                            goal=np.array([1, 1, 1.0]), success=True, collisions=0)
    out = plot_trajectories(tmp_path / "t.png", [trial], [_box([0.4, 0.4, 0], [0.6, 0.6, 2])])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # rebuild to inspect the legend text (the PNG is pixels): the figure legend lists every colour's meaning
    plt.close("all")
    from polycc.report import flights

    captured = {}
    orig = plt.Figure.legend

    def spy(self, *a, **k):
        captured["labels"] = [h.get_label() for h in k.get("handles", [])]
        return orig(self, *a, **k)

    plt.Figure.legend = spy
    try:
        flights.plot_trajectories(tmp_path / "t2.png", [trial], [_box([0.4, 0.4, 0], [0.6, 0.6, 2])])
    finally:
        plt.Figure.legend = orig
    assert {"reached the goal", "stuck / timeout", "collision", "start", "goal", "stored polytopes"} <= \
        set(captured["labels"])
    assert out.is_file()
