"""Monte Carlo union volume and wasted volume (polycc.geometry.union_volume)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.geometry.halfplanes import axis_box
from polycc.geometry.union_volume import in_voxels, union_volume, union_waste


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(*[st.integers(-20, 20)] * 3), min_size=1, max_size=40, unique=True),
       st.floats(0.01, 1.0), st.floats(-5, 5))
def test_in_voxels_matches_a_direct_lookup(vox, g, o):
    idx = np.array(vox, np.int64)
    origin = np.array([o, -o, 0.5 * o])
    test = in_voxels(idx, origin, g)
    rng = np.random.default_rng(0)
    pts = origin + (rng.uniform(-22, 22, (500, 3))) * g
    want = {tuple(v) for v in vox}
    got = test(pts)
    for p, inside in zip(pts, got):
        assert inside == (tuple(np.floor((p - origin) / g).astype(int)) in want)
    assert test(origin + (idx + 0.5) * g).all()  # voxel centres


def test_waste_of_an_exact_cover_is_zero_and_of_a_loose_one_is_right():
    g = 0.1
    idx = np.array([[i, j, k] for i in range(3) for j in range(2) for k in range(2)], np.int64)
    occ = in_voxels(idx, np.zeros(3), g)
    exact = [axis_box([0, 0, 0], [0.3, 0.2, 0.2])]
    box = [(np.array([0, 0, 0.0]), np.array([0.3, 0.2, 0.2]))]
    vol, _, waste, wci = union_waste(exact, box, occ, samples=20_000)
    assert waste == 0.0 and wci == 0.0 and abs(vol - 0.012) < 1e-3
    loose = [axis_box([0, 0, 0], [0.3, 0.2, 0.3])]  # half a layer of voxels too tall: waste 0.006
    box = [(np.array([0, 0, 0.0]), np.array([0.3, 0.2, 0.3]))]
    vol, vci, waste, wci = union_waste(loose, box, occ, samples=200_000)
    assert abs(waste - 0.006) <= wci + 1e-12 and wci < 1e-4
    assert abs(vol - 0.018) <= vci + 1e-12
    assert union_volume(loose, box, samples=200_000)[0] == vol  # same samples, same estimate
