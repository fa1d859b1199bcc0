"""Code generation: the fixed-size C header ``polytopes.h`` and ``manifest.json``.

Templates (package data, ``polycc/codegen/templates/``) hold structure only; every number is formatted here as an
exact C99 hexadecimal float literal, so the C reads bit for bit what Python packed.
No timestamps: the same input and options give the same bytes.
"""

from __future__ import annotations

import json
from pathlib import Path

import jinja2
import numpy as np

from polycc.budget.cycle_model import worst_cycles
from polycc.onboard.layout import SCENE_FORMAT, PackedScene, pack_scene
from polycc.version import __version__

MANIFEST_FORMAT = "polycc-scene/1"


def c_float(x) -> str:
    """Exact C99 hex literal of a float32 value, e.g. ``0x1.8p-3f``."""
    v = float(np.float32(x))
    if v == 0.0:
        return "-0x0p+0f" if np.signbit(v) else "0x0p+0f"
    if not np.isfinite(v):
        raise ValueError(f"cannot emit non-finite float {v}")
    mant, exp = v.hex().split("p")
    mant = mant.rstrip("0").rstrip(".")
    return f"{mant}p{exp}f"


def _env() -> jinja2.Environment:
    return jinja2.Environment(
        loader=jinja2.PackageLoader("polycc.codegen", "templates"),
        undefined=jinja2.StrictUndefined,
        keep_trailing_newline=True,
        autoescape=False,
    )


def c_record(rec: np.void) -> str:
    """A C99 designated initializer for one structured-array record (floats exact, ints unsigned)."""
    parts = []
    for name in rec.dtype.names:
        v = rec[name]
        if np.ndim(v):
            inner = ", ".join(_c_scalar(x) for x in np.asarray(v).ravel())
            parts.append(f".{name} = {{ {inner} }}")
        else:
            parts.append(f".{name} = {_c_scalar(v)}")
    return "{ " + ", ".join(parts) + " }"


def _c_scalar(v) -> str:
    if isinstance(v, (np.floating, float)):
        return c_float(v)
    iv = int(v)
    return f"{iv}u" if iv >= 0 else str(iv)


def render_header(packed: PackedScene, meta: dict) -> str:
    """The text of polytopes.h for a packed scene; ``meta`` holds provenance and budgets."""
    opts = meta.get("options", {})
    return _env().get_template("polytopes.h.j2").render(
        version=__version__,
        scene_name=meta.get("scene", {}).get("name", "?"),
        scene_sha256=meta.get("scene", {}).get("sha256", "?"),
        options_line=" ".join(f"{k}={v}" for k, v in sorted(opts.items())) or "(defaults)",
        transform_line=json.dumps(meta.get("transform")),
        floater_line=meta.get("floater_line", "none"),
        kappa=f"{meta['kappa']:g}",
        kappa_literal=c_float(meta["kappa"]),
        worst_cycles=int(meta.get("worst_cycles", np.ceil(worst_cycles(packed)))),
        typical_cycles=int(meta.get("typical_cycles", 0)),
        n_clusters=packed.n_clusters,
        n_polys=packed.n_polys,
        n_planes=packed.n_planes,
        n_normals=packed.n_normals,
        quantum=c_float(packed.quantum),
        quantum_text=f"{float(packed.quantum):g}",
        data_bytes=packed.flash_bytes(),
        budget_bytes=int(meta["budget_bytes"]),
        max_planes=int(meta["max_planes"]),
        binding=meta.get("binding", "none"),
        conservativeness=meta.get("conservativeness_text", "n/a"),
        layout_format=SCENE_FORMAT,
        normals=[c_record(r) for r in packed.normals],
        planes=[c_record(r) for r in packed.planes],
        polys=[c_record(r) for r in packed.polys_raw],
        clusters=[c_record(r) for r in packed.clusters],
        coord_bound=c_float(packed.coord_bound),
        log_lmax=c_float(packed.log_lmax),
        index=_index_context(packed),
    )


def _index_context(packed: PackedScene) -> dict | None:
    ix = packed.index
    if ix is None:
        return None
    r = ix.record()
    arrays = []
    for name, a in zip(("cell_list", "children", "list_start", "entries", "poly_first"), ix.arrays()):
        vals = [f"{int(v)}u" for v in np.asarray(a)]
        if len(vals) % 2:
            vals.append("0u")  # pad to 4 bytes, as the image
        if not vals:
            vals = ["0u", "0u"]  # C has no empty arrays (not counted in the bytes)
        arrays.append((name, vals))
    return {"dims": " x ".join(str(d) for d in ix.dims), "cell": f"{ix.cell:g}", "n_lists": ix.n_lists,
            "n_entries": len(ix.entries), "cap_text": f"{float(ix.cap):g}", "cap": c_float(ix.cap),
            "bytes": ix.nbytes(), "arrays": arrays, "ox": c_float(r["ox"]), "oy": c_float(r["oy"]),
            "oz": c_float(r["oz"]), "inv_cell": c_float(r["inv_cell"]), "nx": r["nx"], "ny": r["ny"],
            "nz": r["nz"], "n_inner": ix.n_inner}


def manifest(packed: PackedScene, meta: dict) -> dict:
    """Machine-readable description; ``polytopes`` hold the values exactly as the C decodes them."""
    return {
        "format": MANIFEST_FORMAT,
        "polycc_version": __version__,
        "units": "m",
        "frame": "world (scene frame after the transform)",
        "layout_format": SCENE_FORMAT,
        "transform": meta.get("transform"),
        "kappa": float(meta["kappa"]),
        "scene": meta.get("scene", {}),
        "options": meta.get("options", {}),
        "scene_settings": meta.get("scene_settings"),
        "polytopes": [{"halfplanes": h.astype(np.float64).tolist()} for h in packed.polytopes()],
        "stats": meta.get("stats", {}),
    }


def write_outputs(out_dir: str | Path, packed: PackedScene | list, meta: dict | None = None) -> dict:
    """Write ``polytopes.h``, ``manifest.json`` and ``scene.bin`` into ``out_dir``; returns the manifest.

    ``scene.bin`` is :meth:`PackedScene.to_bytes` (read it back with
    :func:`polycc.onboard.layout.scene_from_bytes`): the same bytes as the header's arrays, for the
    host simulator and the tests.

    ``packed`` may also be a list of (H, 4) half-plane arrays with unit normals (tests);
    :func:`pack_scene` quantizes them outward (vertices from qhull).
    ``meta`` defaults: kappa 100, budgets equal to what is used.
    """
    if not isinstance(packed, PackedScene):
        packed = pack_scene([np.asarray(h) for h in packed])
    meta = dict(meta or {})
    meta.setdefault("kappa", 100.0)
    meta.setdefault("budget_bytes", packed.flash_bytes())
    meta.setdefault("max_planes", packed.n_planes)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "polytopes.h").write_text(render_header(packed, meta))
    man = manifest(packed, meta)
    (out / "manifest.json").write_text(json.dumps(man, indent=1, sort_keys=False) + "\n")
    (out / "scene.bin").write_bytes(packed.to_bytes())
    return man


def load_manifest_polytopes(out_dir: str | Path) -> list[np.ndarray]:
    """The stored polytopes of a build folder, as (H, 4) float64 arrays [nx, ny, nz, d]."""
    man = json.loads((Path(out_dir) / "manifest.json").read_text())
    return [np.asarray(p["halfplanes"], np.float64).reshape(-1, 4) for p in man["polytopes"]]
