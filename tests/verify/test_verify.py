"""Independent certification: passes on real covers, fails loudly on broken ones; the CLI pair."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.cli import main
from polycc.cover.build import build_cover
from polycc.occupancy.exact import voxelize
from polycc.occupancy.grid import OccupancyGrid
from polycc.scene.ellipsoids import Ellipsoids, quaternion_to_rotation
from polycc.scene.writers import write_gaussian_ply
from polycc.verify.certify import FamilyArrays, certify_all_levels, check_level, read_family, sample_ellipsoids


def random_ellipsoids(n, seed, span=0.3, log_sigma=(np.log(0.003), np.log(0.06))):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1)[:, None]
    return Ellipsoids(rng.uniform(-span, span, (n, 3)), quaternion_to_rotation(q),
                      np.exp(rng.uniform(*log_sigma, (n, 3))), 1.0, opacity=np.full(n, 0.9, np.float32))


def test_ellipsoid_samples_lie_on_and_inside():
    ell = random_ellipsoids(50, 1)
    pts = sample_ellipsoids(ell.centers, ell.axes(), 64, np.random.default_rng(0)).reshape(50, 64, 3)
    M = ell.whitening()
    r = np.linalg.norm(np.einsum("eij,epj->epi", M, pts - ell.centers[:, None]), axis=2)
    assert np.all(r <= 1 + 1e-9)
    assert np.mean(np.isclose(r, 1.0)) >= 0.5  # half on the surface (plus the 6 axis tips)


@settings(max_examples=12)
@given(st.integers(1, 40), st.integers(0, 10_000), st.sampled_from(["paper", "delta"]))
def test_random_ellipsoids_are_covered_at_every_level(n, seed, cost):
    ell = random_ellipsoids(n, seed)
    grid = voxelize(ell, 0.05)
    fam = build_cover(grid, 1, cost)
    path_arrays = FamilyArrays.from_family(fam)
    assert certify_all_levels(path_arrays, grid.indices) == []
    for lvl in {fam.n_max, max(1, fam.n_max // 2), 1}:
        rep = check_level(path_arrays, lvl, grid.indices, ell.centers, ell.axes(), 64, 5_000, 0)
        assert rep.voxels_uncovered == 0 and rep.points_uncovered == 0
        assert rep.points_sampled >= max(64 * n, 5_000)


def test_tolerance_counts_against_the_cover():
    grid = OccupancyGrid(np.array([[2, 3, 4]]), 0.05, np.array([0.01, 0.02, 0.03]))
    fam = build_cover(grid, 1)
    fa = FamilyArrays.from_family(fam)
    assert check_level(fa, 1, grid.indices, mc_samples=0).voxels_uncovered == 0
    fa.planes = fa.planes.copy()
    fa.planes[0, 3] -= 2e-9  # beyond the 1 nm outward margin: one corner face is now outside
    assert check_level(fa, 1, grid.indices, mc_samples=0).voxels_uncovered == 1


def test_certificate_catches_a_shrunken_merged_polytope():
    rng = np.random.default_rng(2)
    grid = OccupancyGrid(np.unique(rng.integers(0, 12, (150, 3)), axis=0), 0.05)
    fam = build_cover(grid, 1)
    fa = FamilyArrays.from_family(fam)
    assert certify_all_levels(fa, grid.indices) == []
    node = fam.n_max + (fam.n_max - 1) // 2  # a merged node in the middle of the sequence
    a, b = fa.plane_ptr[node], fa.plane_ptr[node + 1]
    fa.planes = fa.planes.copy()
    fa.planes[a:b, 3] -= 0.05  # shrink it by one voxel on every side
    fails = certify_all_levels(fa, grid.indices)
    assert fails and all(u != 0 for _, u in fails)


def test_conservativeness_of_a_box_is_one():
    r = [np.arange(0, 6)] * 3
    idx = np.stack(np.meshgrid(*r, indexing="ij"), -1).reshape(-1, 3)
    grid = OccupancyGrid(idx, 0.1, np.zeros(3))
    fam = build_cover(grid, 1)
    rep = check_level(FamilyArrays.from_family(fam), 1, grid.indices, mc_samples=20_000)
    assert rep.conservativeness == pytest.approx(1.0, abs=3 * rep.conservativeness_ci + 1e-6)


@pytest.fixture
def small_scene(tmp_path):
    ply = tmp_path / "scene.ply"
    write_gaussian_ply(ply, random_ellipsoids(300, 7))
    return ply


def test_cli_cover_then_verify(small_scene, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["cover", str(small_scene), "-o", str(out), "--voxel", "0.05", "--mc-samples", "2000",
                 "--plot-n", "1,5"]) == 0
    for f in ("cover.npz", "cover.json", "tradeoff.png", "cover_n1.png", "cover_n5.png"):
        assert (out / f).is_file(), f
    capsys.readouterr()
    rc = main(["verify", str(out), str(small_scene), "--voxel", "0.05", "--min-samples", "20000",
               "--mc-samples", "5000", "--report", str(tmp_path / "rep.json")])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert rc == 0, last
    assert last.startswith("verify: PASS") and "voxels checked" in last and "points sampled" in last
    assert "uncovered voxels 0 points 0" in last and "conservativeness" in last
    fam = read_family(out)
    assert fam.meta["merge_cost"] in ("paper", "delta") and fam.meta["merge_cost_requested"] == "best"


def test_cli_verify_fails_on_a_broken_cover(small_scene, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["cover", str(small_scene), "-o", str(out), "--no-compare", "--plot-n", "", "--mc-samples",
                 "1000"]) == 0
    z = dict(np.load(out / "cover.npz"))
    z["planes"][:, 3] -= 0.02  # every polytope shrinks by 2 cm
    np.savez(out / "cover.npz", **z)
    capsys.readouterr()
    rc = main(["verify", str(out), str(small_scene), "--min-samples", "10000", "--mc-samples", "1000",
               "--levels", "1"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert rc == 1 and last.startswith("verify: FAIL")


def test_cli_user_errors(tmp_path, small_scene, capsys):
    assert main(["verify", str(tmp_path / "nothing"), str(small_scene)]) == 2
    assert main(["cover", str(small_scene), "-o", str(tmp_path / "o"), "--neighborhood", "-1"]) == 2
    err = capsys.readouterr().err
    assert "polycc cover: error" in err and "--neighborhood" in err
