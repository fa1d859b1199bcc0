"""unique_rows (the fast row de-duplication the cover and the size estimate use) is np.unique(axis=0)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from polycc.geometry.lattice import unique_rows, voxel_corner_points


@settings(max_examples=200, deadline=None)
@given(arrays(np.int64, st.tuples(st.integers(0, 60), st.integers(1, 4)), elements=st.integers(-4, 4)))
def test_unique_rows_is_numpy_unique(a):
    assert np.array_equal(unique_rows(a), np.unique(a, axis=0))


@settings(max_examples=100, deadline=None)
@given(arrays(np.int64, st.tuples(st.integers(1, 27), st.just(3)), elements=st.integers(-2, 2)))
def test_voxel_corner_points_are_the_sorted_distinct_corners(idx):
    pts = (idx[:, None, :] + np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)])).reshape(-1, 3)
    assert np.array_equal(voxel_corner_points(idx), np.unique(pts, axis=0))
