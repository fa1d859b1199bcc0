"""Build -> compile the generated polytopes.h with the kernel (cffi) -> the bit-exact suite
runs on the generated scene.

The C reads the header's own ``polycc_scene`` (not a scene assembled by the host); its bytes must
equal ``PackedScene.to_bytes()`` of the build (``scene.bin``), and ``polycc_step`` must match
``polycc.onboard.barrier.step`` on that PackedScene as uint32 patterns of psi, grad, u_nom, u and the flags.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from polycc.cli import main
from polycc.onboard import barrier as B
from polycc.onboard.layout import scene_from_bytes
from polycc.testing.bitexact import PARAMS, assert_bitexact, edge_states, states
from polycc.testing.files import SCENES

N_STATES = 100_000 if os.environ.get("CI") else 10_000

BUILDS = {
    # a real capture (metres: the ring is about 1 m across at scale 1)
    "ring": lambda tmp: ["build", str(SCENES / "ring_10k.splat"), "--scale", "1.0", "--voxel", "0.02",
                         "--flash-kb", "8", "--mc-samples", "5000", "-o", str(tmp / "out")],
    # the synthetic demo arena (polycc demo-scene)
    "demo": lambda tmp: ["build", str(tmp / "arena.ply"), "--flash-kb", "8", "--mc-samples", "5000",
                         "-o", str(tmp / "out")],
}


@pytest.fixture(scope="module", params=sorted(BUILDS))
def built(request, tmp_path_factory):
    name = request.param
    if name == "ring" and not SCENES.is_dir():
        pytest.skip(f"real scenes not found at {SCENES}")
    tmp = tmp_path_factory.mktemp(f"gen-{name}")
    if name == "demo":
        assert main(["demo-scene", str(tmp / "arena.ply")]) == 0
    assert main(BUILDS[name](tmp)) == 0
    from polycc.sim.kernel_ffi import load_generated

    out = tmp / "out"
    packed = scene_from_bytes((out / "scene.bin").read_bytes())
    return name, out, packed, load_generated(out / "polytopes.h")


def test_generated_header_holds_the_packed_bytes(built):
    from polycc.sim.kernel_ffi import generated_image

    name, out, packed, mod = built
    assert generated_image(mod) == (out / "scene.bin").read_bytes(), f"{name}: header bytes != PackedScene"
    # the manifest's polytopes are the decoded values, exactly as the C reads them
    man = json.loads((out / "manifest.json").read_text())
    dec = packed.polytopes()
    assert len(man["polytopes"]) == len(dec) == packed.n_polys
    for m, h in zip(man["polytopes"], dec):
        assert np.array_equal(np.asarray(m["halfplanes"], np.float64), h.astype(np.float64))
    assert man["stats"]["bytes"] == packed.flash_bytes()


@pytest.mark.parametrize("pi", [0, 1, 2])
def test_generated_scene_bitexact(built, pi):
    from polycc.sim.kernel_ffi import generated_step_batch

    name, _, packed, mod = built
    x, goal = states_in(packed, N_STATES if pi == 0 else N_STATES // 5, seed=40 + pi)
    out = generated_step_batch(mod, PARAMS[pi], x, goal)
    assert_bitexact(B.step(packed, PARAMS[pi], x, goal), out, f"generated {name} params {pi}")
    assert np.mean(out["flags"] & B.FLAG_INVALID == 0) > 0.9
    assert np.mean(out["flags"] & B.FLAG_ACTIVE != 0) > 0.01


def test_generated_scene_edge_cases(built):
    from polycc.sim.kernel_ffi import generated_step_batch

    name, _, packed, mod = built
    x, goal = edge_states(packed)
    out = generated_step_batch(mod, PARAMS[0], x, goal)
    assert_bitexact(B.step(packed, PARAMS[0], x, goal), out, f"generated edge {name}")
    assert out["flags"][4] & B.FLAG_INSIDE, "the centre of a polytope is inside"


def states_in(packed, n, seed):
    """The bit-exact suite's states (room, near faces, far), the room mapped onto this scene's box."""
    x, goal = states(packed, n, seed)
    P = packed.polys
    c = np.stack([P["cx"], P["cy"], P["cz"]], axis=1).astype(np.float64)
    lo, hi = c.min(0) - 0.5, c.max(0) + 0.5
    n_room = n // 2
    rng = np.random.default_rng(seed + 1000)
    x[:n_room] = rng.uniform(lo, hi, (n_room, 3)).astype(np.float32)
    goal[:] = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    return x, goal
