"""Budget, outward reduction and quantization, code generation (polycc build)."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from polycc.budget.reduce import reduce_planes
from polycc.budget.select import Budget, plane_counts, select
from polycc.cli import main
from polycc.codegen.header import c_float, load_manifest_polytopes
from polycc.geometry.halfplanes import hull_halfplanes, polytope_vertices
from polycc.occupancy.grid import OccupancyGrid
from polycc.testing.files import CHECKOUT as REPO
from polycc.testing.files import SCENES


def random_hull(rng, n=25, scale=0.3):
    pts = rng.normal(size=(n, 3)) * scale + rng.uniform(-3, 3, 3)
    h = ConvexHull(pts)
    return hull_halfplanes(pts), pts[h.vertices]


def test_reduction_only_enlarges_and_stays_bounded():
    rng = np.random.default_rng(2)
    polys = [random_hull(rng, n=40) for _ in range(6)]
    total = sum(len(h) for h, _ in polys)
    cap = total // 2
    red, added = reduce_planes(polys, cap)
    assert sum(len(h) for h in red) <= cap and added >= 0
    for (h, v), r in zip(polys, red):
        assert np.all(v @ r[:, :3].T <= r[:, 3] + 1e-12)  # every original vertex still inside
        assert polytope_vertices(r, v.mean(0)) is not None  # bounded
    assert reduce_planes(polys, 3 * len(polys)) is None  # below 4 planes per polytope: impossible


def test_c_float_is_exact():
    for x in [0.0, 1.0, -2.5, 1e-7, 3.4e38, np.float32(0.1), -np.float32(1 / 3)]:
        lit = c_float(x)
        assert lit.endswith("f")
        assert np.float32(float.fromhex(lit[:-1])) == np.float32(x)


def _ring_args(tmp_path, kb, extra=()):
    return ["build", str(SCENES / "ring_10k.splat"), "--scale", "1.0", "--voxel", "0.02",
            "--flash-kb", str(kb), "--mc-samples", "20000", "-o", str(tmp_path / f"out{kb}"), *extra]


def _check_cover(out, grid: OccupancyGrid):
    """Every corner of every occupied voxel satisfies all half-planes of some stored polytope."""
    polys = load_manifest_polytopes(out)
    lo = grid.lower_corners()
    corners = np.concatenate([lo + grid.voxel_size * np.array([(c >> 0) & 1, (c >> 1) & 1,
                                                               (c >> 2) & 1]) for c in range(8)])
    inside_any = np.zeros(len(lo), bool)
    for h in polys:
        ok = np.all(corners @ h[:, :3].T <= h[:, 3], axis=1).reshape(8, -1).all(axis=0)
        inside_any |= ok
    return inside_any


@pytest.fixture(scope="module")
def built4(tmp_path_factory):
    if not SCENES.is_dir():
        pytest.skip("real scenes not found (../shared/scenes)")
    tmp = tmp_path_factory.mktemp("build4")
    assert main(_ring_args(tmp, 4)) == 0
    return tmp


@pytest.mark.parametrize("kb", [2, 4])
def test_build_fits_budget_covers_every_voxel_and_compiles(tmp_path, built4, kb):
    if kb == 4:
        tmp_path = built4
    else:
        assert main(_ring_args(tmp_path, kb)) == 0
    out = tmp_path / f"out{kb}"
    man = json.loads((out / "manifest.json").read_text())
    assert man["format"] == "polycc-scene/1" and man["units"] == "m" and man["kappa"] == 100.0
    assert man["stats"]["bytes"] <= kb * 1024
    from polycc.cover.family import CoverFamily
    fam = CoverFamily.load(out)
    grid = OccupancyGrid(fam.grid_indices, fam.voxel_size, fam.origin)
    assert _check_cover(out, grid).all()
    assert (out / "report.png").stat().st_size > 10_000
    src = out / "t.c"
    src.write_text('#include "polytopes.h"\nint main(void) { return (int)polycc_scene.n_polys == '
                   '(int)POLYCC_SCENE_N_POLYS ? 0 : 1; }\n')
    cc = ["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-Wdouble-promotion", f"-I{REPO / 'firmware_app' / 'src'}",
          f"-I{out}"]
    subprocess.run([*cc, str(src), "-o", str(out / "t")], check=True)
    subprocess.run([str(out / "t")], check=True)
    if shutil.which("arm-none-eabi-gcc"):
        subprocess.run(["arm-none-eabi-gcc", "-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16",
                        "-Os",
                        "-std=gnu11", "-Wall", "-Wdouble-promotion", "-Werror", "-fno-math-errno", "-ffp-contract=off",
                        f"-I{REPO / 'firmware_app' / 'src'}", f"-I{out}", "-c", str(src), "-o", str(out / "t.o")],
                            check=True)


def test_byte_model_is_exact_and_within_budget(built4):
    """Predicted bytes (layout formula from the counts) == what the header declares, <= budget."""
    from polycc.budget.select import data_bytes
    out = built4 / "out4"
    st_ = json.loads((out / "manifest.json").read_text())["stats"]
    index = st_["onboard"]["index"]["bytes"] if st_["onboard"]["index"] else 0  # the spatial index counts too
    assert st_["bytes"] == data_bytes(st_["n"], st_["halfplanes"], st_["normals"]) + index <= 4 * 1024
    assert st_["normals"] <= st_["normals_before_reduction"] or st_["normal_table_cap"] is not None
    head = (out / "polytopes.h").read_text()
    assert f"#define POLYCC_SCENE_DATA_BYTES {st_['bytes']}u" in head
    assert f"#define POLYCC_SCENE_N_NORMALS {st_['normals']}u" in head
    for c in st_["candidates"]:
        assert c["bytes"] <= 4 * 1024


def test_build_is_deterministic(tmp_path, built4):
    assert main(_ring_args(tmp_path, 4)) == 0
    for name in ("polytopes.h", "manifest.json"):
        assert (tmp_path / "out4" / name).read_bytes() == (built4 / "out4" / name).read_bytes()


def test_impossible_budget_says_smallest_that_works(tmp_path, scenes_dir, capsys):
    assert main(_ring_args(tmp_path, 0.1)) == 2
    err = capsys.readouterr().err
    assert "--flash-kb" in err and "or more" in err and "Traceback" not in err


def test_halfplane_budget_binds(tmp_path, scenes_dir):
    assert main(_ring_args(tmp_path, 64, ["--max-halfplanes", "120"])) == 0
    man = json.loads((tmp_path / "out64" / "manifest.json").read_text())
    assert man["stats"]["halfplanes"] <= 120 and man["stats"]["binding_budget"].split()[0] == "halfplanes"


def test_plane_counts_match_materialised(built4):
    from polycc.cover.family import CoverFamily
    fam = CoverFamily.load(built4 / "out4")
    counts = plane_counts(fam)
    for n in sorted({1, 2, fam.n_max // 2, fam.n_max}):
        assert counts[n] == fam.halfplane_count(n)


def test_unbounded_four_plane_set_is_detected():
    """Regression: qhull's half-space intersection returned finite 'vertices' for an
    unbounded 4-plane set produced by reduction (capture arena, 8 KiB)."""
    from polycc.geometry.halfplanes import is_bounded
    # three planes of a corner plus one that does not close it: unbounded along (1,1,1)
    n = np.array([[-1, 0, 0], [0, -1, 0], [0, 0, -1], [1, -1, 0] / np.sqrt(2)])
    h = np.c_[n, np.ones(4)]
    assert not is_bounded(n)
    assert polytope_vertices(h, np.zeros(3)) is None
    tet = np.array([[-1, 0, 0], [0, -1, 0], [0, 0, -1], np.ones(3) / np.sqrt(3)])
    assert is_bounded(tet)
    assert polytope_vertices(np.c_[tet, np.ones(4)], np.zeros(3) - 0.1) is not None


def test_rate_budget_bounds_worst_case_time(tmp_path, scenes_dir):
    assert main(_ring_args(tmp_path, 64, ["--rate-hz", "1000", "--cpu-share", "0.1"])) == 0
    man = json.loads((tmp_path / "out64" / "manifest.json").read_text())
    assert man["stats"]["modelled_us"]["worst_us"] <= 0.1 / 1000 * 1e6
    assert man["stats"]["binding_budget"].split()[0] == "rate"


def test_capped_normal_tables_fit_and_are_compared(built4):
    """Candidates over (n, T): a capped table holds at most T normals, every candidate fits the
    budget exactly by the layout formula, and the choice is the least conservative."""
    from polycc.budget.select import data_bytes
    from polycc.cover.family import CoverFamily
    fam = CoverFamily.load(built4 / "out4")
    budget = Budget(3 * 1024)
    best, cands, binding = select(fam, budget, mc_samples=5000, normal_caps=(None, 24, 12))
    assert any(c.max_normals is not None for c in cands), "a capped table was tried"
    for c in cands:
        assert c.bytes == data_bytes(c.n, c.n_planes, c.n_normals) <= budget.flash_bytes
        if c.max_normals is not None:
            assert c.n_normals <= c.max_normals
    low = min(cands, key=lambda c: c.conservativeness)
    tied = [c for c in cands if c.conservativeness <= low.conservativeness + low.conservativeness_ci]
    assert best in tied and best.n == min(c.n for c in tied)  # least conservative up to MC ties, then fewest
    assert binding.split()[0] in ("flash", "none")


def test_per_polytope_plane_limit_is_enforced():
    """Regression: a donut build at 8 KiB kept a 273-plane polytope; the layout allows 256."""
    rng = np.random.default_rng(4)
    polys = [random_hull(rng, n=80) for _ in range(2)]
    red, _ = reduce_planes(polys, 10_000, per_polytope=20)
    assert all(len(h) <= 20 for h in red)
    for (h, v), r in zip(polys, red):
        assert np.all(v @ r[:, :3].T <= r[:, 3] + 1e-12)


def test_boxes_cannot_lose_a_plane():
    """Every plane of a box is essential (dropping one opens it): the reduction refuses at once
    instead of searching, and never returns an unbounded polytope."""
    from polycc.geometry.halfplanes import axis_box

    boxes = []
    for i in range(5):
        h = axis_box([i, 0, 0], [i + 0.5, 1, 1])
        boxes.append((h, np.array([[x, y, z] for x in (i, i + 0.5) for y in (0, 1) for z in (0, 1)], float)))
    assert reduce_planes(boxes, 29) is None  # 5 boxes need 30
    red, added = reduce_planes(boxes, 30)
    assert added == 0.0 and sum(len(h) for h in red) == 30


def test_cost_cache_does_not_change_the_reduction():
    rng = np.random.default_rng(7)
    polys = [random_hull(rng, n=40) for _ in range(4)]
    cache: dict = {}
    plain = reduce_planes(polys, 40)
    for _ in range(2):  # second pass hits the cache
        cached = reduce_planes(polys, 40, cost_cache=cache)
        assert len(cache) == 8  # per polytope: its original drop costs and its recorded greedy
        assert all(np.array_equal(a, b) for a, b in zip(plain[0], cached[0])) and plain[1] == cached[1]


def _one_heap_greedy(polytopes, max_planes, per_polytope=None):
    """The reduction as it was written before the per-polytope streams (one heap over every plane of
    every polytope, no cache): the oracle of the test below."""
    import heapq

    from polycc.budget.reduce import MIN_PLANES, all_drop_costs, recompute_cost
    from polycc.geometry.halfplanes import polytope_volume

    cap = per_polytope if per_polytope is not None else 1 << 30
    if sum(len(h) for h, _ in polytopes) <= max_planes and all(len(h) <= cap for h, _ in polytopes):
        return [np.asarray(h) for h, _ in polytopes], 0.0
    if max_planes < MIN_PLANES * len(polytopes) or cap < MIN_PLANES:
        return None
    planes = [np.asarray(h, np.float64) for h, _ in polytopes]
    ids = [np.arange(len(h)) for h in planes]
    interior = [np.asarray(v, np.float64).mean(axis=0) for _, v in polytopes]
    volume = [polytope_volume(np.asarray(v, np.float64)) for _, v in polytopes]
    version = [0] * len(planes)
    added = [0.0]
    costs = lambda k: all_drop_costs(planes[k], interior[k], volume[k])  # noqa: E731 (every plane at once)

    def entries(ks):
        heap = [(c, k, int(ids[k][j]), version[k]) for k in ks if len(planes[k]) > MIN_PLANES
                for j, c in enumerate(costs(k)) if np.isfinite(c)]
        heapq.heapify(heap)
        return heap

    need = sum(len(planes[k]) if len(planes[k]) <= MIN_PLANES else
               max(MIN_PLANES, sum(1 for c in costs(k) if not np.isfinite(c))) for k in range(len(planes)))
    if need > max_planes:
        return None

    def drop_until(heap, done):
        while not done():
            if not heap:
                return False
            c, k, orig, ver = heapq.heappop(heap)
            rows = np.flatnonzero(ids[k] == orig)
            if not rows.size or len(planes[k]) <= MIN_PLANES:
                continue
            j = int(rows[0])
            if ver != version[k]:
                c = recompute_cost(planes[k], j, interior[k], volume[k])
                if np.isfinite(c):
                    heapq.heappush(heap, (c, k, orig, version[k]))
                continue
            planes[k], ids[k] = np.delete(planes[k], j, axis=0), np.delete(ids[k], j)
            volume[k] += c
            version[k] += 1
            added[0] += c
        return True

    for k in [k for k in range(len(planes)) if len(planes[k]) > cap]:
        if not drop_until(entries([k]), lambda k=k: len(planes[k]) <= cap):
            return None
    if not drop_until(entries(range(len(planes))), lambda: sum(len(h) for h in planes) <= max_planes):
        return None
    return planes, added[0]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), fracs=st.lists(st.floats(0.15, 0.95), min_size=1, max_size=4),
       per_polytope=st.sampled_from([None, 12, 24]), dup=st.booleans())
def test_recorded_streams_reduce_exactly_as_one_heap(seed, fracs, per_polytope, dup):
    """The per-polytope streams (recorded once, replayed by later calls through the cache) give the one-heap
    greedy's result bit for bit: the same planes kept and the same added volume, for any caps, for calls
    sharing a cache in any order, and with a polytope listed twice."""
    rng = np.random.default_rng(seed)
    polys = [random_hull(rng, n=int(rng.integers(8, 45))) for _ in range(int(rng.integers(1, 6)))]
    if dup:
        polys.append(polys[0])
    total = sum(len(h) for h, _ in polys)
    cache: dict = {}
    for f in fracs:
        want = _one_heap_greedy(polys, int(total * f), per_polytope)
        for got in (reduce_planes(polys, int(total * f), per_polytope),
                    reduce_planes(polys, int(total * f), per_polytope, cost_cache=cache)):
            assert (want is None) == (got is None)
            if want is not None:
                assert got[1] == want[1] and len(got[0]) == len(want[0])
                assert all(np.array_equal(a, b) for a, b in zip(got[0], want[0]))


def test_record_cache_packs_identical_bytes():
    from polycc.onboard.layout import pack_scene
    from polycc.testing.synthetic import random_hull_polytopes

    polys = random_hull_polytopes(np.random.default_rng(3), 12)
    cache: dict = {}
    ref = pack_scene(polys).to_bytes()
    assert pack_scene(polys, record_cache=cache).to_bytes() == ref
    assert pack_scene(polys[:6] + polys[6:], record_cache=cache).to_bytes() == ref
    assert sum(1 for k in cache if k[0] != "needs_box") == 12  # one record per polytope


def test_binding_text_names_a_full_budget():
    """Regression: the 1.5M room filled 65,516 of 65,536 bytes and the summary said 'none',
    because a larger n had fit with a coarser normal table."""
    from types import SimpleNamespace as NS

    from polycc.budget.select import binding_text

    fam = NS(n_max=7866)
    cand = lambda n, planes, cap, T=None: NS(n=n, n_planes=planes, dropped=0, max_normals=T,  # noqa: E731
                                            caps={"flash": cap})
    best = cand(1172, 9946, 9950, 256)
    assert binding_text(fam, best, [best, cand(1241, 10300, 10310, 64)]).startswith("flash (full;")
    assert binding_text(fam, best, [best]) == "flash"
    roomy = cand(800, 5000, 9000)
    assert binding_text(fam, roomy, [roomy, cand(1200, 8000, 9000)]).startswith("none (larger n fit")
    whole = cand(7866, 5000, 9000)
    assert binding_text(fam, whole, [whole]) == "none (the whole sub-cover fits)"


def test_a_rate_miss_does_not_end_the_search(monkeypatch):
    """Regression: once one candidate missed the rate budget every larger n was skipped, but the certified
    worst case is not monotone in n, and the 2.5 cm room's cover fell from n = 26 to n = 5
    (conservativeness 1.33 -> 18). A larger n that fits must still be realised."""
    import types

    from polycc.budget import select as sel

    fits = {(5, None): True, (10, None): False, (26, None): True, (20, 8): True, (40, 8): False, (50, 8): True}
    asked = []

    def fake_realise(family, n, T, *a, **k):
        asked.append((n, T))
        return types.SimpleNamespace(n=n, max_normals=T, meets_rate=fits[(n, T)])

    monkeypatch.setattr(sel, "realise", fake_realise)
    pairs = list(fits)
    out = sel._realise_many(None, None, pairs, {n: 0 for n, _ in pairs}, 1.0, 0)
    assert asked == pairs
    assert [(c.n, c.max_normals) for c in out if c.meets_rate] == [(5, None), (26, None), (20, 8), (50, 8)]


def test_a_rate_miss_caps_the_planes_of_every_n():
    """Regression: when no candidate met the rate, the first halved n that met it (n = 1) ended the search:
    the 150k-splat room at 2.5 cm got one polytope (conservativeness 3.94) where n = 3 and n = 14 with their
    half-planes capped met the rate at 1.04. Every n realised is now tried with the cap, largest first."""
    from dataclasses import dataclass

    from polycc.budget import select as sel

    @dataclass
    class C:
        n: int
        max_normals: None
        worst_cycles: float
        conservativeness: float
        meets_rate: bool

    asked = []

    def fake_realise_all(budget, pairs, *a, **k):
        (n, _), = pairs
        asked.append((n, budget.max_halfplanes))
        return [C(n, None, budget.rate_cycles / 2, 1.0 + 0.001 * n, False)]

    done = [C(n, None, 1e9, c, m) for n, c, m in [(1, 3.94, True), (3, 1.044, False), (14, 1.038, False)]]
    out = sel._tightened(Budget(65536, None, 67200.0, 0.3), done, fake_realise_all)
    assert [n for n, _ in asked] == [14, 3, 1] and all(cap >= 4 * n for n, cap in asked)
    assert {c.n for c in out if c.meets_rate and c.conservativeness < 1.1} >= {3, 14}


def test_the_selection_does_not_depend_on_the_workers(built4, monkeypatch):
    """The drop costs computed in forked workers and the candidates realised there give the same
    candidates, bit for bit, as one process (every family counts as large here); with 2 workers every
    prefill round is forked, with 3 every round runs in this process (STREAMS_IN_PROCESS)."""
    from polycc.budget import select as sel
    from polycc.cover.family import CoverFamily

    fam = CoverFamily.load(built4 / "out4")
    monkeypatch.setattr(sel, "PARALLEL_MIN_POLYTOPES", 1)
    runs = []
    for w, in_process in ((1, 64), (2, 0), (3, 10**9)):
        monkeypatch.setattr(sel, "STREAMS_IN_PROCESS", in_process)
        runs.append(select(fam, Budget(3 * 1024), mc_samples=5000, normal_caps=(None, 24, 12), workers=w))
    ref = runs[0][1]
    assert any(c.dropped for c in ref) and any(c.max_normals is not None for c in ref)  # reduced, capped: real work
    for best, cands, _ in runs[1:]:
        assert (best.n, best.max_normals) == (runs[0][0].n, runs[0][0].max_normals)
        assert [(c.n, c.max_normals, c.dropped, c.bytes, c.conservativeness) for c in cands] == [
            (c.n, c.max_normals, c.dropped, c.bytes, c.conservativeness) for c in ref]
        for a, b in zip(cands, ref):
            assert all(np.array_equal(x, y) for x, y in zip(a.packed.polytopes(), b.packed.polytopes()))


def test_capped_tables_are_skipped_only_where_the_uncapped_neighbours_miss_the_rate():
    import types

    from polycc.budget.select import _capped_worth_trying

    def c(n, meets):
        return types.SimpleNamespace(n=n, meets_rate=meets)

    rate = Budget(65536, None, 67200.0, 0.3)
    done = [c(10, False), c(26, True), c(52, False), c(105, False), c(630, False)]
    assert _capped_worth_trying(30, done, rate)  # 26 below meets
    assert _capped_worth_trying(26, done, rate)
    assert _capped_worth_trying(20, done, rate)  # 26 above meets
    assert not _capped_worth_trying(60, done, rate)  # 52 and 105 miss
    assert not _capped_worth_trying(1014, done, rate)  # above everything: 630 misses
    assert _capped_worth_trying(5, [c(10, True)], rate)
    assert _capped_worth_trying(60, done, Budget(65536))  # no rate budget: always
    assert _capped_worth_trying(60, done, Budget(65536, None, 67200.0, None))  # no index: the rate caps planes
    assert _capped_worth_trying(60, [], rate)


def test_capped_tables_leave_their_neighbours_index_bytes_free(built4):
    """Regression: with a rate budget and an index, a capped table's reduction spent every byte it freed on
    half-planes and left its index only what the coarsest one needed (the 6M-splat room's capped candidates
    missed the rate 6-8x). Now it leaves free the index bytes of the uncapped neighbours that meet the rate."""
    import types

    from polycc.budget.select import _reserving
    from polycc.cover.family import CoverFamily

    fam = CoverFamily.load(built4 / "out4")
    budget = Budget(4 * 1024, None, 100_000.0, 0.3)
    best, cands, _ = select(fam, budget, mc_samples=5000, normal_caps=(None, 24, 12))
    plain = [c for c in cands if c.max_normals is None]
    capped = [c for c in cands if c.max_normals is not None]
    assert capped, "a capped table was tried"
    reserve = _reserving(budget, [(c.n, c.max_normals) for c in capped], plain).index_reserve
    for c in capped:
        assert reserve[c.n] > 0
        assert c.bytes - c.packed.index.nbytes() <= budget.flash_bytes - reserve[c.n]
    assert best.meets_rate

    def cand(n, meets, ix):
        return types.SimpleNamespace(n=n, meets_rate=meets, packed=types.SimpleNamespace(
            index=types.SimpleNamespace(nbytes=lambda: ix)))

    done = [cand(10, True, 500), cand(20, False, 900), cand(40, True, 700)]
    assert _reserving(budget, [(15, 24), (30, 24), (50, 12)], done).index_reserve == {15: 500, 30: 700, 50: 700}
    assert _reserving(budget, [(25, 24)], [cand(20, False, 900), cand(30, False, 1)]).index_reserve is None
    assert _reserving(Budget(4096), [(15, 24)], done) == Budget(4096)  # no rate budget: nothing reserved
    assert Budget(4096, index_reserve={15: 400}).caps(15, 10)["flash"] == Budget(4096).caps(15, 10)["flash"] - 100


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), q=st.floats(0.0, 1.0), per_polytope=st.sampled_from([None, 12, 24]))
def test_streams_recorded_past_a_key_serve_every_greedy_that_stops_below_it(seed, q, per_polytope):
    """A greedy whose drops all have keys <= lam reads no pop of a stream past the first one above lam
    (_Stream.extend records up to it): the selection's prefill relies on this to do the reductions' qhull work
    in parallel. Same result as without the record, and not one pop computed on demand."""
    from polycc.budget import reduce as red

    rng = np.random.default_rng(seed)
    polys = [random_hull(rng, n=int(rng.integers(8, 40))) for _ in range(int(rng.integers(1, 6)))]
    store: dict = {}
    streams = [red.polytope_stream(store, np.asarray(h, np.float64), np.asarray(v, np.float64), per_polytope)
               for h, v in polys]
    if not all(s.ok for s in streams):
        return
    keys = sorted(k[0] for s in streams for k in s.heap if np.isfinite(k[0]))
    if not keys:
        return
    lam = keys[min(int(q * len(keys)), len(keys) - 1)] * (1 + 1e-9)  # between keys (no tie at lam)
    for s in streams:
        s.extend(lam)
    recorded = [len(s.ops) for s in streams]
    drops = sum(s.upto(lam)[0] for s in streams)
    cap = sum(len(h) for h, _ in polys) - sum(len(s.pre_costs) for s in streams) - drops
    got = red.reduce_planes(polys, cap, per_polytope, cost_cache=store)
    assert [len(s.ops) for s in streams] == recorded  # nothing read past the record
    want = reduce_planes(polys, cap, per_polytope)
    assert (got is None) == (want is None)
    if want is not None:
        assert got[1] == want[1] and all(np.array_equal(a, b) for a, b in zip(got[0], want[0]))


def test_the_prefill_records_what_the_first_reductions_read(built4, monkeypatch):
    """After the selection's prefill (the streams made and extended on the workers), the first reduction of
    every candidate replays recorded pops only: no drop cost is left for the candidates' workers to compute."""
    from polycc.budget import reduce as red
    from polycc.budget import select as sel
    from polycc.cover.family import CoverFamily
    from polycc.onboard.layout import MAX_POLY_PLANES

    fam = CoverFamily.load(built4 / "out4")
    budget = Budget(3 * 1024)
    normals = sel._Normals(fam)
    counts = plane_counts(fam, normals.merged_per_node)
    ns, _ = sel.candidate_ns(fam, budget, normals.count, counts)
    before = {n: normals.count(n) for n in ns}
    r = sel._Realiser(fam, normals, 1.0, 5000, 2, counts)
    r._prefill(budget, [(n, None) for n in ns], before)
    store = r.caches["drop_costs"]
    assert sum(len(s.ops) for k, s in store.items() if k[0] == "stream") > 0
    computed = []
    for name in ("drop_cost", "all_drop_costs"):  # one plane by qhull, every plane at once
        real = getattr(red, name)
        monkeypatch.setattr(red, name, lambda *a, real=real: computed.append(1) or real(*a))
    reduced = 0
    for n in ns:
        polys = fam.materialise(n)
        rows = [sel._merged_rows(p) for p in polys]
        cap = budget.capacity(n, before[n])
        if sum(len(h) for h in rows) > cap:
            reduced += 1
            red.reduce_planes([(h, p.vertices) for h, p in zip(rows, polys)], cap, per_polytope=MAX_POLY_PLANES,
                              cost_cache=store)
    assert reduced >= 2 and not computed


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), rows=st.integers(1, 300), grid=st.sampled_from([4, 64, 4096]),
       axis_share=st.floats(0.0, 1.0))
def test_normal_keys_are_the_ids_of_np_unique_rows(seed, rows, grid, axis_share):
    """normal_keys' one-int64-per-row ids are those of np.unique(axis=0) on the snapped, gcd-reduced normals
    (the same labels, in the same order), with repeats and axis normals in the mix."""
    from polycc.budget.select import normal_keys

    rng = np.random.default_rng(seed)
    n = rng.normal(size=(rows, 3))
    axis = rng.random(rows) < axis_share
    n[axis] = np.eye(3)[rng.integers(0, 3, axis.sum())] * rng.choice([-1, 1], (axis.sum(), 1))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n = n[rng.integers(0, rows, rows)]  # repeats
    planes = np.c_[n, rng.normal(size=rows)]
    m = np.rint(planes[:, :3] * grid).astype(np.int64)
    g = np.gcd.reduce(np.abs(m), axis=1)
    g[g == 0] = 1
    _, want = np.unique(m // g[:, None], axis=0, return_inverse=True)
    assert np.array_equal(normal_keys(planes, grid), want.ravel())


@settings(max_examples=200, deadline=None)
@given(weights=st.lists(st.floats(0.0, 1e6), min_size=1, max_size=300), workers=st.integers(1, 8))
def test_guided_chunks_keep_every_item_once_in_order_and_shrink(weights, workers):
    """The prefill's chunks (heaviest first, handed out as workers come free): every item once, in order, none
    empty; each closed chunk at least its share of what was left (or 1 % of the total), so their number stays
    small, and the last ones are no heavier than that share."""
    from polycc.budget.select import CHUNK_SHARE, _guided

    weights = sorted(weights, reverse=True)
    chunks = _guided(list(range(len(weights))), weights, workers)
    assert [i for c in chunks for i in c] == list(range(len(weights))) and all(chunks)
    total = sum(weights) or 1.0
    left = total
    for c in chunks[:-1]:
        w = sum(weights[i] for i in c)
        share = max(left / (CHUNK_SHARE * workers), 0.01 * total)
        assert w >= share * (1 - 1e-9)
        assert w - weights[c[-1]] < share * (1 + 1e-9)  # closed by its last item
        left -= w
    assert len(chunks) <= 101 + CHUNK_SHARE * workers * 6


def test_stream_weights_count_the_qhull_side_above_the_c_limit():
    """Regression: a stream's weight was m (m + 50) for every m; above the C's 128 planes each drop cost is one
    qhull, 15-25x slower per unit (1.5M-splat room at 2.5 cm: 18 such polytopes took 8.4 of the first prefill
    round's 10.1 s), and several shared one chunk."""
    from polycc.budget.select import NATIVE_MAX_PLANES, _stream_weight

    m = NATIVE_MAX_PLANES
    assert _stream_weight(m) == m * (m + 50.0)
    assert _stream_weight(m + 18) / ((m + 18) * (m + 68.0)) == pytest.approx(14.6)  # 146 planes: 5.1e-6 / 3.5e-7
    assert _stream_weight(271) / (271 * 321.0) == pytest.approx(27.1)  # 8.9e-6 / 3.5e-7 = 25


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 12), st.booleans(), st.integers(200, 6000),
       st.sampled_from([None, 3000.0, 20_000.0]))
def test_choose_index_skips_only_top_grids_that_cannot_fit(seed, n, boxes, max_bytes, rate):
    """Regression: choose_index no longer lists a top grid whose cells alone exceed the bytes left (the 6M-splat
    room's capped candidates asked for a 48 KB grid with 5-6 KB free, six times each); the same index is chosen,
    and the bound it uses is below every index build_index makes."""
    from unittest import mock

    import polycc.budget.select as S
    from polycc.onboard.index import build_index, grid_box, index_bytes_at_least, index_slack
    from polycc.testing.synthetic import small_scene

    sc = small_scene(seed, n, boxes)
    budget = Budget(65536, None, rate, 0.3, 100.0)
    got = S.choose_index(sc, budget, max_bytes)
    with mock.patch.object(S, "index_bytes_at_least", lambda *a: 0):
        ref = S.choose_index(sc, budget, max_bytes)
    assert (got is None) == (ref is None)
    if got is not None:
        assert got.cell == ref.cell and all(np.array_equal(a, b) for a, b in zip(got.arrays(), ref.arrays()))
    box = grid_box(sc, float(np.float32(0.3)) + index_slack(sc, 100.0))
    for cell in S.INDEX_CELLS:
        ix = build_index(sc, 0.3, cell, 100.0, target=rate, max_bytes=max_bytes, box=box)
        assert index_bytes_at_least(box, cell, sc.n_polys) <= ix.nbytes()
