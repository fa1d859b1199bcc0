"""Arena builders from the real captures: normalisation, the capture arena, the benchmark room."""

from __future__ import annotations

import numpy as np
import pytest

from polycc.demo.arenas import (
    CAPTURE_ARENA_LAYOUT,
    capture_arena,
    normalize_to_size,
    rotation_to_z_up,
    tiled_room,
)
from polycc.errors import PolyccError
from polycc.scene.ellipsoids import Ellipsoids
from polycc.testing.files import SCENES  # noqa: E402


def blob(n=2000, seed=0, floaters=0):
    rng = np.random.default_rng(seed)
    c = rng.uniform([10, 20, 30], [14, 22, 31], size=(n, 3))  # 4 x 2 x 1 file units
    if floaters:
        c[:floaters] = rng.uniform(-1000, 1000, size=(floaters, 3))
    return Ellipsoids(c, np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), np.full((n, 3), 0.01), 1.0,
                      np.ones(n, np.float32), None)


def test_normalize_to_size_ignores_floaters_but_keeps_them():
    e = blob(floaters=5)
    out = normalize_to_size(e, 1.0)
    assert len(out) == len(e)
    lo, hi = np.percentile(out.centers, [0.5, 99.5], axis=0)
    assert max(hi - lo) == pytest.approx(1.0)
    assert (lo[2]) == pytest.approx(0.0, abs=1e-12)
    assert 0.5 * (lo[0] + hi[0]) == pytest.approx(0.0, abs=1e-12)
    assert 0.5 * (lo[1] + hi[1]) == pytest.approx(0.0, abs=1e-12)
    s = 1.0 / (np.percentile(e.centers[:, 0], 99.5) - np.percentile(e.centers[:, 0], 0.5))
    np.testing.assert_allclose(out.sigmas, e.sigmas * s)
    np.testing.assert_allclose(np.ptp(out.centers, axis=0), np.ptp(e.centers, axis=0) * s)  # floaters moved too
    assert normalize_to_size(e, 2.5).sigmas[0, 0] == pytest.approx(2.5 * out.sigmas[0, 0])
    with pytest.raises(PolyccError):
        normalize_to_size(blob(1), 1.0)


@pytest.mark.parametrize("up", [(0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1), (1, 0, 0), (1, 2, 3)])
def test_rotation_to_z_up(up):
    R = rotation_to_z_up(up)
    u = np.asarray(up, float) / np.linalg.norm(up)
    np.testing.assert_allclose(R @ u, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


@pytest.fixture(scope="module")
def arena_of_captures():
    if not SCENES.is_dir():
        pytest.skip(f"real scenes not found at {SCENES}")
    return capture_arena(SCENES)


def test_capture_arena(arena_of_captures):
    ell = arena_of_captures
    assert 300_000 < len(ell) < 400_000
    lo, hi = ell.bounds()
    assert np.all(lo[:2] > -2.1) and np.all(hi[:2] < 2.1)
    assert 0.9 < hi[2] < 1.2
    for _name, (x, y) in CAPTURE_ARENA_LAYOUT:  # each capture stands upright on its spot
        near = np.all(np.abs(ell.centers[:, :2] - (x, y)) < 0.5, axis=1) & (ell.centers[:, 2] > 0.05)
        assert near.sum() > 50_000
        z = ell.centers[near, 2]
        assert np.percentile(z, 99.5) > 0.3


def test_capture_arena_uprights(arena_of_captures):
    """The plant's pot (brown/grey, low saturation) is at the bottom, the leaves above it."""
    ell = arena_of_captures
    x, y = CAPTURE_ARENA_LAYOUT[0][1]
    near = np.all(np.abs(ell.centers[:, :2] - (x, y)) < 0.6, axis=1) & (ell.centers[:, 2] > 0.02)
    rgb = ell.colors[near].astype(float)
    green = (rgb[:, 1] > rgb[:, 0] + 10) & (rgb[:, 1] > rgb[:, 2] + 10)
    z = ell.centers[near, 2]
    assert np.median(z[green]) > np.median(z[~green])


def test_tiled_room_small(scenes_dir):
    ell = tiled_room(scenes_dir, target=400_000, seed=1)
    assert len(ell) == 400_000
    lo, hi = ell.bounds()
    assert np.all(lo[:2] > -5.2) and np.all(hi[:2] < 5.2) and hi[2] < 3.0
    again = tiled_room(scenes_dir, target=400_000, seed=1)
    np.testing.assert_array_equal(again.centers, ell.centers)


@pytest.mark.slow
def test_tiled_room_benchmark_size(scenes_dir):
    ell = tiled_room(scenes_dir)
    assert len(ell) == 1_500_000
    lo, hi = np.percentile(ell.centers, [0.5, 99.5], axis=0)
    assert np.all(hi[:2] - lo[:2] > 8.0) and hi[2] > 1.5 and hi[2] < 3.0
