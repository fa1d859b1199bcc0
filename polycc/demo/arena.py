"""A synthetic flight arena as 3D Gaussian splats, in metres, z up.

The arena is a 6 m x 6 m room (x, y in [-3, 3], floor at z = 0, ceiling height 3 m
for planning) holding three upright hoops on thin stands, three poles and three boxes.
Splats are flat discs sampled on the surfaces, as a trainer makes them: two standard
deviations of a few millimetres to 2 cm in the tangent plane, one of 1-2 mm along the
surface normal, rotated to the surface, with opacities and colours.

The layout is fixed; ``seed`` only changes where the splats fall on the surfaces, their
sizes, opacities and colour noise. :func:`demo_arena_description` gives the layout as a
JSON-ready dict (see its docstring), including start and goal points for a flight
through each hoop.
"""

from __future__ import annotations

import numpy as np

from polycc.scene.ellipsoids import Ellipsoids

ARENA_FORMAT = "polycc-arena/1"
ROOM_MIN = (-3.0, -3.0, 0.0)
ROOM_MAX = (3.0, 3.0, 3.0)
# Distance from a hoop's centre to the suggested start and goal, along its normal, metres.
FLIGHT_HALF_LENGTH_M = 1.2

_S2 = float(np.sqrt(0.5))
# name, centre (m), unit normal (horizontal: the hoops stand upright), centreline
# radius R (m), tube radius r (m), colour. The free opening has radius R - r.
HOOPS = (
    ("hoop_0", (-1.2, -1.4, 0.9), (1.0, 0.0, 0.0), 0.44, 0.040, (235, 110, 20)),
    ("hoop_1", (0.9, 0.3, 1.4), (0.0, 1.0, 0.0), 0.49, 0.040, (40, 170, 70)),
    ("hoop_2", (-1.0, 1.5, 1.8), (_S2, _S2, 0.0), 0.40, 0.035, (40, 90, 220)),
)
HOOP_STAND_RADIUS_M = 0.02
# name, base (x, y) (m), radius (m), height (m), colour.
POLES = (
    ("pole_0", (1.9, -1.7), 0.06, 2.6, (225, 225, 225)),
    ("pole_1", (-2.3, 0.2), 0.05, 2.2, (200, 40, 40)),
    ("pole_2", (2.2, 2.1), 0.08, 2.8, (230, 200, 60)),
)
# name, centre of the footprint (x, y) (m), size (sx, sy, sz) (m), yaw (deg), colour.
# Boxes stand on the floor.
BOXES = (
    ("box_0", (1.9, -0.3), (0.6, 0.6, 0.5), 20.0, (150, 105, 60)),
    ("box_1", (0.0, 2.3), (0.9, 0.5, 0.4), 0.0, (120, 80, 50)),
    ("box_2", (-0.2, -2.4), (0.5, 0.5, 1.1), -15.0, (90, 110, 130)),
)

# Mean splat spacing on each kind of surface, metres (sets the splat count and size).
_SPACING = {"floor": 0.02, "hoop": 0.007, "stand": 0.008, "pole": 0.012, "box": 0.012}
_TANGENT_SIGMA_RANGE_M = (0.002, 0.02)
_NORMAL_SIGMA_RANGE_M = (0.001, 0.002)


# ----------------------------------------------------------------------------- splats
def surface_frames(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(N, 3, 3) proper rotations whose third column is the unit normal; the tangent
    axes (columns 0 and 1) are turned by a random angle about the normal."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    a = np.zeros_like(n)
    use_x = np.abs(n[:, 0]) < 0.9
    a[use_x, 0] = 1.0
    a[~use_x, 1] = 1.0
    t1 = a - np.sum(a * n, axis=1, keepdims=True) * n
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    phi = rng.uniform(0.0, 2.0 * np.pi, size=(len(n), 1))
    u = np.cos(phi) * t1 + np.sin(phi) * t2
    v = np.cross(n, u)
    return np.stack([u, v, n], axis=2)


def surface_splats(
    rng: np.random.Generator,
    points: np.ndarray,
    normals: np.ndarray,
    spacing: float,
    colors: np.ndarray,
    k: float = 1.0,
) -> Ellipsoids:
    """Flat disc splats at ``points`` (metres) on a surface with the given ``normals``.

    The tangent sigmas scatter (log-normally) around 0.7 x ``spacing``, clipped to
    2 mm-2 cm; the normal sigma is 1-2 mm. ``colors`` is (N, 3) or (3,) RGB; a little
    noise is added. Opacities lean towards opaque, as in trained scenes.
    """
    n = len(points)
    tang = spacing * 0.7 * rng.lognormal(0.0, 0.25, size=(n, 2))
    tang = np.clip(tang, *_TANGENT_SIGMA_RANGE_M)
    norm = rng.uniform(*_NORMAL_SIGMA_RANGE_M, size=(n, 1))
    base = np.broadcast_to(np.asarray(colors, dtype=np.float64), (n, 3))
    rgb = np.clip(base + rng.normal(0.0, 8.0, size=(n, 3)), 0, 255).round().astype(np.uint8)
    opacity = np.clip(rng.beta(8.0, 1.5, size=n), 0.05, 1.0).astype(np.float32)
    return Ellipsoids(
        centers=np.asarray(points, dtype=np.float64),
        rotations=surface_frames(np.asarray(normals, dtype=np.float64), rng),
        sigmas=np.concatenate([tang, norm], axis=1),
        k=k,
        opacity=opacity,
        colors=rgb,
    )


def _count(area: float, spacing: float) -> int:
    return max(1, int(round(area / spacing**2)))


# ----------------------------------------------------------------------------- surfaces
def sample_rectangle(rng, n, origin, u, v):
    """``n`` uniform points on the parallelogram origin + a u + b v, a, b in [0, 1]."""
    ab = rng.uniform(0.0, 1.0, size=(n, 2))
    return np.asarray(origin) + ab[:, :1] * np.asarray(u) + ab[:, 1:] * np.asarray(v)


def hoop_basis(normal) -> np.ndarray:
    """3x3 rotation whose third column is ``normal``; for a horizontal normal the second
    column is +z (so the hoop's lowest point is at centre - (R + r) z)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    up = np.array([0.0, 0.0, 1.0])
    e1 = np.cross(up, n)
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.array([1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return np.stack([e1, e2, n], axis=1)


def sample_torus(rng, n, center, normal, R, r):
    """``n`` points uniform by area on a torus (centreline radius R, tube r) and their normals."""
    u = rng.uniform(0.0, 2.0 * np.pi, size=n)
    vs = []
    got = 0
    while got < n:  # rejection: the area element is proportional to R + r cos v
        cand = rng.uniform(0.0, 2.0 * np.pi, size=2 * (n - got) + 16)
        keep = cand[rng.uniform(0.0, 1.0, size=cand.size) * (R + r) <= R + r * np.cos(cand)]
        vs.append(keep[: n - got])
        got += len(vs[-1])
    v = np.concatenate(vs)
    nl = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    pl = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)], axis=1)
    B = hoop_basis(normal)
    return np.asarray(center) + pl @ B.T, nl @ B.T


def sample_cylinder(rng, spacing, base_xy, radius, z0, z1, cap=True):
    """Points and normals on an upright cylinder's side (z0..z1) and, if ``cap``, its top disc."""
    h = z1 - z0
    n_side = _count(2.0 * np.pi * radius * h, spacing)
    th = rng.uniform(0.0, 2.0 * np.pi, size=n_side)
    z = rng.uniform(z0, z1, size=n_side)
    nrm = np.stack([np.cos(th), np.sin(th), np.zeros(n_side)], axis=1)
    pts = np.stack([base_xy[0] + radius * nrm[:, 0], base_xy[1] + radius * nrm[:, 1], z], axis=1)
    if not cap:
        return pts, nrm
    n_cap = _count(np.pi * radius**2, spacing)
    rr = radius * np.sqrt(rng.uniform(0.0, 1.0, size=n_cap))
    tc = rng.uniform(0.0, 2.0 * np.pi, size=n_cap)
    cp = np.stack([base_xy[0] + rr * np.cos(tc), base_xy[1] + rr * np.sin(tc), np.full(n_cap, z1)], axis=1)
    cn = np.tile([0.0, 0.0, 1.0], (n_cap, 1))
    return np.concatenate([pts, cp]), np.concatenate([nrm, cn])


def sample_box(rng, spacing, center_xy, size, yaw_deg):
    """Points and normals on the five visible faces of a box standing on the floor."""
    sx, sy, sz = size
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    hx, hy = sx / 2, sy / 2
    # (origin, u, v, outward normal) in the box frame, origin at the footprint centre.
    faces = [
        ((-hx, -hy, sz), (sx, 0, 0), (0, sy, 0), (0, 0, 1)),
        ((hx, -hy, 0), (0, sy, 0), (0, 0, sz), (1, 0, 0)),
        ((-hx, -hy, 0), (0, sy, 0), (0, 0, sz), (-1, 0, 0)),
        ((-hx, hy, 0), (sx, 0, 0), (0, 0, sz), (0, 1, 0)),
        ((-hx, -hy, 0), (sx, 0, 0), (0, 0, sz), (0, -1, 0)),
    ]
    pts, nrm = [], []
    for o, u, v, nn in faces:
        m = _count(np.linalg.norm(np.cross(u, v)), spacing)
        pts.append(sample_rectangle(rng, m, o, u, v))
        nrm.append(np.tile(nn, (m, 1)).astype(np.float64))
    P = np.concatenate(pts) @ Rz.T + np.array([center_xy[0], center_xy[1], 0.0])
    return P, np.concatenate(nrm) @ Rz.T


def _floor_colors(pts: np.ndarray) -> np.ndarray:
    """A 0.5 m grey checkerboard, so the floor has texture."""
    checker = (np.floor(pts[:, 0] / 0.5) + np.floor(pts[:, 1] / 0.5)) % 2
    return np.where(checker[:, None] > 0, [[110, 110, 115]], [[150, 150, 155]]).astype(np.float64)


def make_floor(rng, lo_xy, hi_xy, spacing: float = _SPACING["floor"], k: float = 1.0) -> Ellipsoids:
    """Splats on the floor plane z = 0 over [lo_xy, hi_xy] (metres), grey checkerboard."""
    w, d = hi_xy[0] - lo_xy[0], hi_xy[1] - lo_xy[1]
    pts = sample_rectangle(rng, _count(w * d, spacing), (lo_xy[0], lo_xy[1], 0.0), (w, 0, 0), (0, d, 0))
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    return surface_splats(rng, pts, nrm, spacing, _floor_colors(pts), k=k)


# ----------------------------------------------------------------------------- arena
def _hoop_bottom_z(center, R, r) -> float:
    return float(center[2] - R - r)


def make_demo_arena(seed: int = 0) -> Ellipsoids:
    """The demo flight arena as ellipsoids (metres, z up, k = 1); deterministic in ``seed``.

    About 200k splats: floor, three hoops on stands, three poles, three boxes.
    """
    rng = np.random.default_rng(seed)
    parts = [make_floor(rng, ROOM_MIN[:2], ROOM_MAX[:2])]
    for _name, c, nrm, R, r, col in HOOPS:
        n = _count(4.0 * np.pi**2 * R * r, _SPACING["hoop"])
        p, q = sample_torus(rng, n, c, nrm, R, r)
        parts.append(surface_splats(rng, p, q, _SPACING["hoop"], col))
        # The stand: a thin rod from the floor up to (just into) the hoop's lowest point.
        p, q = sample_cylinder(
            rng, _SPACING["stand"], c[:2], HOOP_STAND_RADIUS_M, 0.0, _hoop_bottom_z(c, R, r) + r, cap=False
        )
        parts.append(surface_splats(rng, p, q, _SPACING["stand"], (70, 70, 70)))
    for _name, xy, radius, height, col in POLES:
        p, q = sample_cylinder(rng, _SPACING["pole"], xy, radius, 0.0, height)
        parts.append(surface_splats(rng, p, q, _SPACING["pole"], col))
    for _name, xy, size, yaw, col in BOXES:
        p, q = sample_box(rng, _SPACING["box"], xy, size, yaw)
        parts.append(surface_splats(rng, p, q, _SPACING["box"], col))
    return Ellipsoids.concatenate(parts)


def _r(x) -> list[float]:
    return [round(float(v), 6) for v in x]


def demo_arena_description(seed: int = 0, ell: Ellipsoids | None = None) -> dict:
    """The arena's layout as a JSON-ready dict, all lengths in metres, z up::

        {"format": "polycc-arena/1", "name": "demo_arena", "units": "m", "up": [0, 0, 1],
         "seed": 0, "room": {"min": [x, y, z], "max": [x, y, z]},
         "hoops": [{"name", "center": [x, y, z], "normal": [nx, ny, nz] (unit, the flight
                    direction), "radius": free opening radius R - r, "major_radius": R,
                    "tube_radius": r, "stand_radius", "color": [r, g, b]}, ...],
         "poles": [{"name", "base": [x, y, 0], "radius", "height", "color"}, ...],
         "boxes": [{"name", "center": [x, y, z] (box centre), "size": [sx, sy, sz],
                    "yaw_deg", "color"}, ...],
         "flights": [{"name", "hoop": index, "start": [x, y, z], "goal": [x, y, z]}, ...],
         "start": flights[0].start, "goal": flights[0].goal,
         "n_splats": N (only when ``ell`` is given), "bounds": {"min", "max"} of the splats}

    Each flight is a straight line along the hoop's normal through its centre, starting
    and ending ``FLIGHT_HALF_LENGTH_M`` from it, clear of every other object.
    """
    hoops, flights = [], []
    for i, (name, c, nrm, R, r, col) in enumerate(HOOPS):
        n = np.asarray(nrm, dtype=np.float64) / np.linalg.norm(nrm)
        hoops.append(
            {
                "name": name,
                "center": _r(c),
                "normal": _r(n),
                "radius": round(R - r, 6),
                "major_radius": R,
                "tube_radius": r,
                "stand_radius": HOOP_STAND_RADIUS_M,
                "color": list(col),
            }
        )
        flights.append(
            {
                "name": f"through_{name}",
                "hoop": i,
                "start": _r(np.asarray(c) - FLIGHT_HALF_LENGTH_M * n),
                "goal": _r(np.asarray(c) + FLIGHT_HALF_LENGTH_M * n),
            }
        )
    desc = {
        "format": ARENA_FORMAT,
        "name": "demo_arena",
        "units": "m",
        "up": [0.0, 0.0, 1.0],
        "seed": int(seed),
        "room": {"min": list(ROOM_MIN), "max": list(ROOM_MAX)},
        "hoops": hoops,
        "poles": [
            {"name": nm, "base": [xy[0], xy[1], 0.0], "radius": rad, "height": h, "color": list(col)}
            for nm, xy, rad, h, col in POLES
        ],
        "boxes": [
            {"name": nm, "center": [xy[0], xy[1], sz[2] / 2], "size": list(sz), "yaw_deg": yaw, "color": list(col)}
            for nm, xy, sz, yaw, col in BOXES
        ],
        "flights": flights,
        "start": flights[0]["start"],
        "goal": flights[0]["goal"],
    }
    if ell is not None:
        lo, hi = ell.bounds()
        desc["n_splats"] = len(ell)
        desc["bounds"] = {"min": _r(lo), "max": _r(hi)}
    return desc


def build_demo_arena(seed: int = 0) -> tuple[Ellipsoids, dict]:
    """``(make_demo_arena(seed), demo_arena_description(seed, that set))``."""
    ell = make_demo_arena(seed)
    return ell, demo_arena_description(seed, ell)
