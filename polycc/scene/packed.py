"""Readers for the packed splat formats people share captures in: SuperSplat/PlayCanvas
``.compressed.ply`` and Niantic ``.spz`` (versions 2, 3 and 4). File frame, file units.

The decoded values are the formats' own definitions (float64 evaluation of the expressions of the
reference readers: PlayCanvas ``read-ply.ts``/``gsplat-compressed-data.js`` and Niantic
``load-spz.cc``); each reader also returns the outward bounds of the quantization
(:class:`polycc.scene.quantized.QuantBounds`), which the loader turns into inflated splats that
hold every encoder input with the same bits. Definitions, bounds and their validation against
files written by ``@playcanvas/splat-transform``: ``docs/formats.md``.

Why hand-written: the decode is a few shifts and lerps, and no library gives the bounds (gsply,
the only maintained Python reader, decodes in float32 with numba and reports none).
"""

from __future__ import annotations

import gzip
import math
import struct
import zlib
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.scene.quantized import QuantBounds, quat_err_smallest

SH_C0 = 0.28209479177387814
SQRT1_2 = math.sqrt(0.5)
# Slack for floating point in the ENCODERS (float32 inputs, float32 log of a linear scale, float32
# arithmetic in Niantic's C++ packer); orders of magnitude below the quantization steps.
SLACK_LOG = 4e-6  # log-scale units
SLACK_QUAT = 2e-6  # per quaternion component
SLACK_REL = 1e-12  # relative, float64 de-quantization


def _raw(positions, sigmas, quats, opacity, colors, bounds, info):
    from polycc.scene.readers import RawSplats

    return RawSplats(positions=positions, sigmas=sigmas, quats=quats, opacity=opacity.astype(np.float32),
                     colors=colors, bounds=bounds, info=info)


def _colors(rgb01: np.ndarray) -> np.ndarray:
    return np.round(np.clip(np.nan_to_num(rgb01), 0.0, 1.0) * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------- .compressed.ply

CHUNK_GEOMETRY = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                  "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")
CHUNK_COLOR = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
CHUNK_SIZE = 256
SCALE_CLAMP = 20.0  # splat-transform clamps the chunk log-scale bounds to [-20, 20]
_LAYOUT = ((21, 11), (11, 10), (0, 11))  # x: bits 21-31, y: bits 11-20, z: bits 0-10


def is_compressed_ply(ply) -> bool:
    """A plyfile PlyData with the SuperSplat chunk/vertex layout."""
    names = [e.name for e in ply.elements]
    return "vertex" in names and "packed_position" in (ply["vertex"].data.dtype.names or ())


def _unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((v >> np.uint32(shift)) & np.uint32((1 << bits) - 1)).astype(np.float64)


def read_compressed_ply(path: Path, ply) -> "RawSplats":  # noqa: F821 - RawSplats (import cycle)
    """SuperSplat / PlayCanvas compressed PLY (18-float chunks, or the older 12-float ones).

    Each splat i belongs to chunk i // 256; its centre and log-scale are 11-10-11 bit unorms of the
    chunk's [min, max] (written round-to-nearest: error <= half a step), the rotation is 'smallest
    three' with 10 bits each (error <= sqrt(2)/2046 per component), colour and alpha 8 bits."""
    names = [e.name for e in ply.elements]
    if "chunk" not in names:
        raise PolyccError(f"{path}: a compressed .ply needs a 'chunk' element before 'vertex' (it has {names}); "
                          "re-export it with SuperSplat or `npx @playcanvas/splat-transform`")
    ch, vx = ply["chunk"].data, ply["vertex"].data
    cnames, vnames = set(ch.dtype.names), set(vx.dtype.names)
    missing = [p for p in CHUNK_GEOMETRY if p not in cnames] + [p for p in PACKED if p not in vnames]
    if missing:
        raise PolyccError(f"{path}: compressed .ply without {', '.join(missing)}; re-export it with SuperSplat or "
                          "`npx @playcanvas/splat-transform`")
    n, nchunks = len(vx), len(ch)
    if nchunks * CHUNK_SIZE < n or (n and nchunks > -(-n // CHUNK_SIZE)):
        raise PolyccError(f"{path}: {n:,} splats need {-(-n // CHUNK_SIZE):,} chunks of {CHUNK_SIZE}, the file has "
                          f"{nchunks:,}; the file is damaged, re-export it")
    ci = np.arange(n) // CHUNK_SIZE
    C = {p: np.asarray(ch[p], np.float64)[ci] for p in cnames}
    pp, pr, ps, pc = (np.asarray(vx[p], np.uint32) for p in PACKED)

    def lerp(lo, hi, t):
        return lo * (1.0 - t) + hi * t

    pos, pos_err, logs, log_err = (np.empty((n, 3)) for _ in range(4))
    sat = np.zeros((n, 3), bool)
    for j, (ax, (sh, bits)) in enumerate(zip("xyz", _LAYOUT)):
        top = (1 << bits) - 1
        lo, hi = C[f"min_{ax}"], C[f"max_{ax}"]
        rng = hi - lo
        pos[:, j] = lerp(lo, hi, _unorm(pp, sh, bits) / top)
        # a degenerate chunk range (< 1e-5) is stored as 0 (or 1 at x >= max): the error is the range
        pos_err[:, j] = np.where(rng < 2e-5, rng, 0.5 * rng / top) + SLACK_REL * (np.abs(lo) + np.abs(hi))
        u = _unorm(ps, sh, bits)
        lo, hi = C[f"min_scale_{ax}"], C[f"max_scale_{ax}"]
        rng = hi - lo
        logs[:, j] = lerp(lo, hi, u / top)
        log_err[:, j] = np.where(rng < 2e-5, rng, 0.5 * rng / top) + SLACK_REL * (np.abs(lo) + np.abs(hi)) + SLACK_LOG
        sat[:, j] = (hi >= SCALE_CLAMP) & (u == top)  # stored at the clamp: unbounded above

    # rotation: 2-bit index of the largest |component| of (w, x, y, z), the other three in index
    # order, 10 bits each, a = (c/1023 - 0.5) sqrt(2); the largest is sqrt(1 - |a|^2)
    small = np.stack([(_unorm(pr, s, 10) / 1023.0 - 0.5) * math.sqrt(2.0) for s in (20, 10, 0)], axis=1)
    largest = (pr >> np.uint32(30)).astype(np.int64)
    quats = np.empty((n, 4))
    order = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    rows = np.arange(n)
    quats[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (small**2).sum(axis=1)))
    for m in range(3):
        quats[rows, order[largest, m]] = small[:, m]
    delta = 0.5 * math.sqrt(2.0) / 1023.0 + SLACK_QUAT
    quat_err = quat_err_smallest(small, delta, math.sqrt(0.75))
    # a code whose three 'small' components are too long for the left-out one to be the largest is
    # not a real encoding (splat-transform writes such garbage for point-only input): not a splat
    quat_err[(small**2).sum(axis=1) > 0.75 + 4 * delta] = np.nan

    alpha = _unorm(pc, 0, 8) / 255.0
    rgb = np.stack([_unorm(pc, s, 8) / 255.0 for s in (24, 16, 8)], axis=1)
    if set(CHUNK_COLOR) <= cnames:
        rgb = np.stack([lerp(C[f"min_{c}"], C[f"max_{c}"], rgb[:, j]) for j, c in enumerate("rgb")], axis=1)
    sigma = np.exp(logs)
    with np.errstate(over="ignore"):
        sigma_hi = np.exp(logs + log_err)
    sigma_hi[sat] = np.inf
    bounds = QuantBounds(pos_err=pos_err, sigma_hi=sigma_hi, quat_err=quat_err,
                         opacity_hi=np.minimum(alpha + 0.5 / 255.0 + 1e-9, 1.0),
                         what="compressed.ply: 11/10/11-bit centre and log-scale per 256-splat chunk, 10-bit "
                              "smallest-three rotation")
    info = {"format": "SuperSplat .compressed.ply", "chunks": nchunks, "chunk_colors": set(CHUNK_COLOR) <= cnames,
            "sh_rest": len(ply["sh"].data.dtype.names) if "sh" in names else 0,
            "comments": [str(c) for c in ply.comments][:4], "saturated_scales": int(sat.any(axis=1).sum())}
    return _raw(pos, sigma, quats, alpha, _colors(rgb), bounds, info)


# ------------------------------------------------------------------------------------- .spz

SPZ_MAGIC = 0x5053474E  # "NGSP" little-endian
_SH_DIM = (0, 3, 8, 15, 24)
COORDINATE_SYSTEMS = ("UNSPECIFIED", "LDB", "RDB", "LUB", "RUB", "LDF", "RDF", "LUF", "RUF",
                      "LFD", "RFD", "LFU", "RFU", "LBD", "RBD", "LBU", "RBU")
_ADOBE_COORDINATE_SYSTEM = 0xADBE0003


def _extensions(buf: bytes) -> list[tuple[int, bytes]]:
    """Extension records ``[u32 type][u32 byteLength][payload]`` back to back."""
    out, off = [], 0
    while off + 8 <= len(buf):
        typ, ln = struct.unpack_from("<II", buf, off)
        out.append((typ, bytes(buf[off + 8: off + 8 + ln])))
        off += 8 + ln
    return out


def _spz_streams(path: Path, raw: bytes):
    """(version, n, sh_degree, fractional_bits, flags, [pos, alpha, colour, scale, rot], extensions)."""
    bad = f"{path}: not a Niantic .spz file"
    if raw[:2] == b"\x1f\x8b":  # v1-v3: one gzip stream, 16-byte header, attribute blocks back to back
        try:
            data = gzip.decompress(raw)
        except (OSError, EOFError, zlib.error) as exc:
            raise PolyccError(f"{path}: truncated or corrupt .spz (gzip: {exc}); re-export or re-download it") from None
        if len(data) < 16:
            raise PolyccError(f"{bad} (header cut short); re-export it")
        magic, version, n, shd, fb, flags, _ = struct.unpack_from("<IIIBBBB", data, 0)
        if magic != SPZ_MAGIC:
            raise PolyccError(f"{bad} (bad magic); re-export it")
        if version not in (2, 3) or shd > 4:
            raise PolyccError(f"{path}: .spz version {version} (SH degree {shd}) is not one polycc reads (2, 3, 4); "
                              "convert it: `npx @playcanvas/splat-transform IN.spz OUT.ply`")
        sizes = [9 * n, n, 3 * n, 3 * n, (3 if version == 2 else 4) * n, 3 * _SH_DIM[shd] * n]
        if len(data) < 16 + sum(sizes):
            raise PolyccError(f"{path}: truncated .spz ({len(data):,} of {16 + sum(sizes):,} bytes after gzip); "
                              "re-export or re-download it")
        out, off = [], 16
        for s in sizes[:5]:
            out.append(np.frombuffer(data, np.uint8, s, off))
            off += s
        off += sizes[5]
        ext = _extensions(data[off:]) if flags & 2 else []
        return version, n, shd, fb, flags, out, ext
    if len(raw) < 32:
        raise PolyccError(f"{bad} (neither gzip nor an NGSP header); re-export it")
    magic, version, n, shd, fb, flags, nstreams, toc = struct.unpack_from("<IIIBBBBI", raw, 0)
    if magic != SPZ_MAGIC:
        raise PolyccError(f"{bad} (neither gzip nor an NGSP header); re-export it")
    if version != 4 or shd > 4:
        raise PolyccError(f"{path}: .spz version {version} (SH degree {shd}) is not one polycc reads (2, 3, 4); "
                          "convert it: `npx @playcanvas/splat-transform IN.spz OUT.ply`")
    import zstandard  # v4: one independent zstd frame per attribute

    sizes = [9 * n, n, 3 * n, 3 * n, 4 * n] + ([3 * _SH_DIM[shd] * n] if shd else [])
    if nstreams != len(sizes) or toc + 16 * nstreams > len(raw):
        raise PolyccError(f"{path}: .spz v4 with {nstreams} streams (expected {len(sizes)}) or a table of contents "
                          "past the end; the file is damaged, re-export it")
    off = toc + 16 * nstreams
    out = []
    dctx = zstandard.ZstdDecompressor()
    for i, want in enumerate(sizes):
        csize, usize = struct.unpack_from("<QQ", raw, toc + 16 * i)
        if usize != want or off + csize > len(raw):
            raise PolyccError(f"{path}: truncated .spz v4 (stream {i}: {usize:,} bytes declared, {want:,} expected); "
                              "re-export or re-download it")
        try:
            buf = dctx.decompress(raw[off: off + csize], max_output_size=usize)
        except zstandard.ZstdError as exc:
            raise PolyccError(f"{path}: corrupt .spz v4 stream {i} ({exc}); re-export or re-download it") from None
        if len(buf) != usize:
            raise PolyccError(f"{path}: .spz v4 stream {i} holds {len(buf):,} bytes, not {usize:,}; re-export it")
        if i < 5:
            out.append(np.frombuffer(buf, np.uint8))
        off += csize
    if off != len(raw):
        raise PolyccError(f"{path}: {len(raw) - off:,} bytes after the last .spz stream; the file was appended to, "
                          "re-export it")
    ext = _extensions(raw[32:toc]) if flags & 2 else []
    return version, n, shd, fb, flags, out, ext


def read_spz(path: Path) -> "RawSplats":  # noqa: F821
    """Niantic .spz v2/v3 (gzip) and v4 (NGSP header + zstd streams), decoded raw (no axis change).

    Centres are 24-bit fixed point with ``fractional_bits`` (error <= 2^-(fb+1)), log-scales 8 bits
    of step 1/16 (sigma within a factor e^(1/32)), rotations smallest-three 9 bits + sign (v3/v4) or
    three 8-bit components with w >= 0 (v2)."""
    raw = Path(path).read_bytes()
    version, n, shd, fb, flags, (P, A, Cb, Sb, Rb), ext = _spz_streams(path, raw)
    coord = None
    for typ, payload in ext:
        if typ == _ADOBE_COORDINATE_SYSTEM and len(payload) >= 4:
            v = struct.unpack_from("<I", payload)[0]
            coord = COORDINATE_SYSTEMS[v] if v < len(COORDINATE_SYSTEMS) else f"unknown ({v})"

    p = P.reshape(n, 3, 3).astype(np.int32)
    fixed = p[:, :, 0] | (p[:, :, 1] << 8) | (p[:, :, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    pos = fixed.astype(np.float64) / float(1 << fb)
    pos_err = np.full((n, 3), 0.5 / float(1 << fb))  # round(x 2^fb) is exact in float32: half a step

    sb = Sb.reshape(n, 3)
    logs = sb.astype(np.float64) / 16.0 - 10.0
    sigma_hi = np.exp(logs + 1.0 / 32.0 + SLACK_LOG)
    sigma_hi[sb == 255] = np.inf  # clamped at the top code: unbounded

    if version == 2:  # x, y, z as round(q 127.5 + 127.5) with w >= 0; w reconstructed
        xyz = Rb.reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.maximum(0.0, 1.0 - (xyz**2).sum(axis=1)))
        quats = np.column_stack([w, xyz])
        quat_err = quat_err_smallest(xyz, 0.5 / 127.5 + SLACK_QUAT, 1.0)
        quat_err[(xyz**2).sum(axis=1) > 1.0 + 3 * (2 / 255)] = np.nan
    else:  # smallest three: 2-bit index of the largest (x, y, z, w order), then (sign << 9 | 9-bit magnitude)
        b = Rb.reshape(n, 4).astype(np.uint32)
        c = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16) | (b[:, 3] << 24)
        largest = (c >> np.uint32(30)).astype(np.int64)
        table = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
        xyzw = np.zeros((n, 4))
        small = np.zeros((n, 3))
        rows = np.arange(n)
        for m in (2, 1, 0):  # the lowest bits hold the highest index
            v = SQRT1_2 * (c & np.uint32(511)).astype(np.float64) / 511.0
            v = np.where(((c >> np.uint32(9)) & np.uint32(1)).astype(bool), -v, v)
            c = c >> np.uint32(10)
            small[:, m] = v
            xyzw[rows, table[largest, m]] = v
        xyzw[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (small**2).sum(axis=1)))
        quats = xyzw[:, [3, 0, 1, 2]]
        delta = SQRT1_2 * 0.5 / 511.0 + SLACK_QUAT
        quat_err = quat_err_smallest(small, delta, math.sqrt(0.75))
        quat_err[(small**2).sum(axis=1) > 0.75 + 4 * delta] = np.nan

    alpha = A.astype(np.float64) / 255.0
    rgb01 = 0.5 + SH_C0 * ((Cb.reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / 0.15)
    bounds = QuantBounds(pos_err=pos_err, sigma_hi=sigma_hi, quat_err=quat_err,
                         opacity_hi=np.minimum(alpha + 0.5 / 255.0 + 1e-6, 1.0),
                         what=f"spz v{version}: centre step 2^-{fb}, log-scale step 1/16, "
                              + ("8-bit x,y,z rotation" if version == 2 else "9-bit smallest-three rotation"))
    info = {"format": f"Niantic .spz v{version}", "sh_degree": shd, "fractional_bits": fb,
            "antialiased": bool(flags & 1), "coordinate_system": coord or "not stated",
            "saturated_scales": int((sb == 255).any(axis=1).sum()),
            "frame_note": "decoded raw: files from SuperSplat/splat-transform hold the .ply frame; files from "
                          "Niantic's library (Scaniverse) hold RUB (y up); `polycc align --up auto` finds up "
                          "either way"}
    return _raw(pos, np.exp(logs), quats, alpha, _colors(rgb01), bounds, info)
