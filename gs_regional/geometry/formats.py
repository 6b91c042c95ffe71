"""The scene in the formats web viewers read, written and read back (numpy, vectorised).

* `.splat` (antimatter15/splat, read by most web viewers): no header, 32 bytes per Gaussian,
  sorted by decreasing ``exp(sum log scales) * opacity``::

      float32 x y z | float32 scale_0..2 (linear) | uint8 r g b a | uint8 quaternion w x y z

  with ``rgb = 0.5 + SH_C0 * dc`` and ``a = sigmoid(opacity)`` as bytes ``v * 255``, and the
  normalised quaternion as ``q * 128 + 128``, clamped to 0..255. The bytes are rounded to the
  nearest (half to even) as the viewer's own PLY converter (main.js, a Uint8ClampedArray) does;
  the repository's convert.py truncates, at most one unit away. No view-dependent colour.
* compressed PLY (`*.compressed.ply`, SuperSplat / PlayCanvas, written as splat-transform's
  `write-compressed-ply` does): Gaussians in Morton order, in chunks of 256. Element `chunk`
  holds per chunk the float32 min and max of the positions, of the log-scales (clamped to
  [-20, 20]) and of the colours ``0.5 + SH_C0 * dc``; element `vertex` holds four uint32 per
  Gaussian: position 11/10/11 bits and log-scale 11/10/11 bits across the chunk's range,
  colour 8/8/8 across the chunk's range with ``sigmoid(opacity)`` in the low 8 bits, and the
  rotation as "smallest three" (2 bits for the index of the largest component in w x y z order,
  then the other three in order, 10 bits each, over ``±1/sqrt(2)``). An optional element `sh`
  holds the f_rest coefficients (INRIA order) as uint8 ``trunc((f / 8 + 0.5) * 256)``, read back
  at the middle of their bin (splat-transform's `decompress-ply`).
* `.spz` (Niantic): through the `gsply` package, an optional extra
  (``pip install 'gs_regional[spz]'``).

Each reader returns a `PlyGaussians`, so a file read back renders like any scene
(`GaussianModel.from_gaussians`). `export_scene` writes the formats an `ExportConfig` asks for.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Tuple

import numpy as np

from gs_regional.config import ConfigError
from gs_regional.geometry.ply import PlyError, PlyGaussians, read_ply, write_ply
from gs_regional.utils.io import atomic_write
from gs_regional.utils.sh import SH_C0

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
assert SPLAT_DTYPE.itemsize == 32
CHUNK_SIZE = 256  # Gaussians per chunk of the compressed PLY
CHUNK_PROPERTIES = (
    "min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
    "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
    "min_r", "min_g", "min_b", "max_r", "max_g", "max_b",
)
VERTEX_PROPERTIES = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
LOG_SCALE_LIMIT = 20.0  # the compressed PLY clamps the chunk's log-scale range to ±20
_CHUNKS_PER_BLOCK = 1024  # compressed PLY: chunks packed at once (262,144 Gaussians), bounds memory
_ALPHA_EPS = 1e-6  # alpha bytes 0 and 255 read back as logit(1e-6) and logit(1 - 1e-6), as splat-transform


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))


def _alpha_logit(alpha: np.ndarray) -> np.ndarray:
    """Opacity logits of alphas in [0, 1] (kept finite: alpha 0 and 1 are moved in by _ALPHA_EPS)."""
    a = np.clip(alpha.astype(np.float64), _ALPHA_EPS, 1.0 - _ALPHA_EPS)
    return np.log(a / (1.0 - a)).astype(np.float32)


def _unit_quats(quats: np.ndarray) -> np.ndarray:
    """(N, 4) float64 unit quaternions (times 1/length, as PlayCanvas' Quat.normalize); a zero
    quaternion becomes the identity."""
    q = quats.astype(np.float64)
    norm = np.sqrt((q * q).sum(1, keepdims=True))
    return np.where(norm == 0, np.array([1.0, 0.0, 0.0, 0.0]), q * (1.0 / np.where(norm == 0, 1.0, norm)))


def _empty_rest(n: int) -> np.ndarray:
    return np.zeros((n, 0, 3), dtype=np.float32)


def _check_not_empty(path: str, g: PlyGaussians) -> None:
    if g.num_gaussians == 0:
        raise ValueError(f"{path}: no Gaussians to write")


# ----- .splat ------------------------------------------------------------------------------------
def splat_order(g: PlyGaussians) -> np.ndarray:
    """The row order of a .splat file: decreasing exp(sum of log-scales) * opacity (stable)."""
    importance = np.exp(g.log_scales.astype(np.float64).sum(1)) * _sigmoid(g.opacity_logits)
    return np.argsort(-importance, kind="stable")


def encode_splat(g: PlyGaussians) -> np.ndarray:
    """The .splat records of `g` (structured array of SPLAT_DTYPE), in `splat_order`."""
    order = splat_order(g)
    out = np.empty(g.num_gaussians, dtype=SPLAT_DTYPE)
    out["position"] = g.means[order]
    out["scale"] = np.exp(g.log_scales[order].astype(np.float64)).astype(np.float32)
    rgba = np.empty((len(order), 4), dtype=np.float64)
    rgba[:, :3] = (0.5 + SH_C0 * g.sh_dc[order].astype(np.float64)) * 255.0
    rgba[:, 3] = _sigmoid(g.opacity_logits[order]) * 255.0
    out["rgba"] = np.clip(np.rint(rgba), 0, 255).astype(np.uint8)
    out["rotation"] = np.clip(np.rint(_unit_quats(g.quats[order]) * 128.0 + 128.0), 0, 255).astype(np.uint8)
    return out


def decode_splat(records: np.ndarray) -> PlyGaussians:
    """Gaussians from .splat records (inverse of `encode_splat` up to its quantisation)."""
    n = len(records)
    rgba = records["rgba"].astype(np.float64) / 255.0
    quats = (records["rotation"].astype(np.float64) - 128.0) / 128.0
    # Scales that underflowed to 0 in float32 come back as the smallest normal float.
    scales = np.maximum(records["scale"].astype(np.float64), np.finfo(np.float32).tiny)
    return PlyGaussians(
        means=np.ascontiguousarray(records["position"], dtype=np.float32),
        sh_dc=((rgba[:, :3] - 0.5) / SH_C0).astype(np.float32),
        sh_rest=_empty_rest(n),
        opacity_logits=_alpha_logit(rgba[:, 3]),
        log_scales=np.log(scales).astype(np.float32),
        quats=_unit_quats(quats).astype(np.float32),
    )


def write_splat(path, g: PlyGaussians) -> None:
    """Write `g` as a .splat file (atomically)."""
    path = os.fspath(path)
    _check_not_empty(path, g)
    records = encode_splat(g)
    with atomic_write(path) as tmp:
        records.tofile(tmp)


def read_splat(path) -> PlyGaussians:
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise PlyError(f"{path}: file not found")
    size = os.path.getsize(path)
    if size == 0 or size % SPLAT_DTYPE.itemsize:
        raise PlyError(f"{path}: a .splat file holds 32 bytes per Gaussian; this one has {size} bytes")
    return decode_splat(np.fromfile(path, dtype=SPLAT_DTYPE))


# ----- compressed PLY ----------------------------------------------------------------------------
def _part1by2(v: np.ndarray) -> np.ndarray:
    """Spread the low 21 bits of `v` (uint64) to every third bit."""
    v = v & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def morton_order(means: np.ndarray) -> np.ndarray:
    """Row order along a 3D Morton (Z-order) curve over the bounding box, 21 bits per axis, so that
    each chunk of 256 holds near neighbours (tight chunk ranges, fine quantisation)."""
    p = means.astype(np.float64)
    lo, hi = p.min(0), p.max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    cells = np.clip((p - lo) / span * (1 << 21), 0, (1 << 21) - 1).astype(np.uint64)
    code = (_part1by2(cells[:, 2]) << np.uint64(2)) | (_part1by2(cells[:, 1]) << np.uint64(1)) | _part1by2(cells[:, 0])
    return np.argsort(code, kind="stable")


def _normalize(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """x in [lo, hi] -> [0, 1] as the reference packer: 0 at or below lo, 1 at or above hi, 0 for a
    range under 1e-5."""
    span = hi - lo
    t = np.where(span < 1e-5, 0.0, (x - lo) / np.where(span < 1e-5, 1.0, span))
    return np.where(x <= lo, 0.0, np.where(x >= hi, 1.0, t))


def _pack_unorm(v: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(v * top + 0.5), 0, top).astype(np.uint32)


def _pack_11_10_11(t: np.ndarray) -> np.ndarray:
    return (_pack_unorm(t[..., 0], 11) << 21) | (_pack_unorm(t[..., 1], 10) << 11) | _pack_unorm(t[..., 2], 11)


def _unpack_11_10_11(v: np.ndarray) -> np.ndarray:
    return np.stack([(v >> 21) / 2047.0, ((v >> 11) & 0x3FF) / 1023.0, (v & 0x7FF) / 2047.0], -1)


def pack_rotations(quats: np.ndarray) -> np.ndarray:
    """(N, 4) w x y z -> uint32 "smallest three": index of the largest |component| (2 bits), the
    other three (sign made so the largest is positive) as 10 bits each over ±1/sqrt(2)."""
    q = _unit_quats(quats)
    largest = np.argmax(np.abs(q), axis=1)  # the first of equal ones, as the reference
    q = np.where(q[np.arange(len(q)), largest][:, None] < 0, -q, q)
    others = q[np.arange(4)[None, :] != largest[:, None]].reshape(-1, 3)
    packed = _pack_unorm(others * (np.sqrt(2) * 0.5) + 0.5, 10)
    return (largest.astype(np.uint32) << 30) | (packed[:, 0] << 20) | (packed[:, 1] << 10) | packed[:, 2]


def unpack_rotations(v: np.ndarray) -> np.ndarray:
    """uint32 "smallest three" -> (N, 4) float64 unit quaternions w x y z."""
    others = np.stack([(v >> 20) & 0x3FF, (v >> 10) & 0x3FF, v & 0x3FF], -1) / 1023.0
    others = (others - 0.5) / (np.sqrt(2) * 0.5)
    largest = (v >> 30).astype(np.int64)
    q = np.empty((len(v), 4), dtype=np.float64)
    keep = np.arange(4)[None, :] != largest[:, None]
    q[keep] = others.reshape(-1)
    q[np.arange(len(v)), largest] = np.sqrt(np.maximum(0.0, 1.0 - (others * others).sum(1)))
    return q


def _pack_chunks(g: PlyGaussians, rows: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Chunk bounds (C, 18) float32 and packed vertices (C*256, 4) uint32 of whole chunks of rows
    (a short last chunk repeats its last Gaussian, which changes no bound)."""
    c = len(rows) // CHUNK_SIZE

    def chunked(a: np.ndarray) -> np.ndarray:  # float32 values as the reference holds them
        return a[rows].astype(np.float32).astype(np.float64).reshape(c, CHUNK_SIZE, -1)

    pos = chunked(g.means)
    log_s = chunked(g.log_scales)
    col = chunked((g.sh_dc.astype(np.float64) * SH_C0 + 0.5).astype(np.float32))
    p_lo, p_hi = pos.min(1), pos.max(1)
    s_lo = np.clip(log_s.min(1), -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT)
    s_hi = np.clip(log_s.max(1), -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT)
    c_lo, c_hi = col.min(1), col.max(1)
    bounds = np.concatenate([p_lo, p_hi, s_lo, s_hi, c_lo, c_hi], 1).astype(np.float32)

    def across(x, lo, hi):
        return _normalize(x, lo[:, None, :], hi[:, None, :])

    packed = np.empty((c, CHUNK_SIZE, 4), dtype=np.uint32)
    packed[..., 0] = _pack_11_10_11(across(pos, p_lo, p_hi))
    packed[..., 1] = pack_rotations(g.quats[rows]).reshape(c, CHUNK_SIZE)
    packed[..., 2] = _pack_11_10_11(across(log_s, s_lo, s_hi))
    rgb = _pack_unorm(across(col, c_lo, c_hi), 8)
    alpha = _pack_unorm(_sigmoid(g.opacity_logits[rows]).reshape(c, CHUNK_SIZE), 8)
    packed[..., 3] = (rgb[..., 0] << 24) | (rgb[..., 1] << 16) | (rgb[..., 2] << 8) | alpha
    return bounds, packed.reshape(-1, 4)


def _pack_sh_rest(g: PlyGaussians, rows: np.ndarray) -> np.ndarray:
    """(len(rows), 3(K-1)) uint8 f_rest coefficients in the INRIA property order (channel-major)."""
    rest = g.sh_rest[rows].astype(np.float64).transpose(0, 2, 1).reshape(len(rows), -1)
    return np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8)


def write_compressed_ply(path, g: PlyGaussians) -> None:
    """Write `g` in the compressed PLY layout of SuperSplat/PlayCanvas (atomically). Name the file
    `*.compressed.ply`: viewers recognise the layout by that suffix."""
    path = os.fspath(path)
    _check_not_empty(path, g)
    n = g.num_gaussians
    n_chunks = -(-n // CHUNK_SIZE)
    order = morton_order(g.means)
    n_rest = 3 * g.sh_rest.shape[1]
    header = ["ply", "format binary_little_endian 1.0", f"element chunk {n_chunks}"]
    header += [f"property float {p}" for p in CHUNK_PROPERTIES]
    header += [f"element vertex {n}"] + [f"property uint {p}" for p in VERTEX_PROPERTIES]
    if n_rest:
        header += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(n_rest)]
    header += ["end_header", ""]
    bounds = np.empty((n_chunks, len(CHUNK_PROPERTIES)), dtype="<f4")
    vertices = np.empty((n, 4), dtype="<u4")
    sh = np.empty((n, n_rest), dtype=np.uint8)
    for first in range(0, n_chunks, _CHUNKS_PER_BLOCK):
        last = min(first + _CHUNKS_PER_BLOCK, n_chunks)
        padded = order[np.minimum(np.arange(first * CHUNK_SIZE, last * CHUNK_SIZE), n - 1)]
        bounds[first:last], packed = _pack_chunks(g, padded)
        end = min(last * CHUNK_SIZE, n)
        vertices[first * CHUNK_SIZE:end] = packed[: end - first * CHUNK_SIZE]
        if n_rest:
            sh[first * CHUNK_SIZE:end] = _pack_sh_rest(g, order[first * CHUNK_SIZE:end])
    with atomic_write(path) as tmp, open(tmp, "wb") as f:
        f.write("\n".join(header).encode("ascii"))
        f.write(bounds.tobytes())
        f.write(vertices.tobytes())
        f.write(sh.tobytes())


def _read_elements(path: str) -> Dict[str, np.ndarray]:
    """The elements of a binary little-endian PLY as structured arrays (one read each)."""
    with open(path, "rb") as f:
        head = f.read(64 * 1024)
        end = head.find(b"end_header\n")
        if not head.startswith(b"ply\n") or end < 0:
            raise PlyError(f"{path}: not a PLY file (no 'ply' magic line or no end_header)")
        lines = head[:end].decode("ascii", "replace").splitlines()
        if "format binary_little_endian 1.0" not in lines:
            raise PlyError(f"{path}: a compressed PLY must be binary little endian")
        types = {"float": "<f4", "uint": "<u4", "uchar": "u1", "int": "<i4", "ushort": "<u2", "short": "<i2",
                 "char": "i1", "double": "<f8", "float32": "<f4", "uint32": "<u4", "uint8": "u1"}
        elements: List[Tuple[str, int, List[Tuple[str, str]]]] = []
        for line in lines:
            words = line.split()
            if words[:1] == ["element"]:
                elements.append((words[1], int(words[2]), []))
            elif words[:1] == ["property"]:
                if words[1] == "list" or words[1] not in types:
                    raise PlyError(f"{path}: unsupported property '{line}' in a compressed PLY")
                elements[-1][2].append((words[2], types[words[1]]))
        f.seek(end + len(b"end_header\n"))
        out = {}
        for name, count, props in elements:
            dtype = np.dtype(props)
            data = np.fromfile(f, dtype=dtype, count=count)
            if len(data) != count:
                raise PlyError(f"{path}: element '{name}' ends after {len(data)} of {count} rows")
            out[name] = data
    return out


def read_compressed_ply(path) -> PlyGaussians:
    """Read a compressed PLY (as PlayCanvas decompresses it) into full-precision arrays."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise PlyError(f"{path}: file not found")
    el = _read_elements(path)
    chunk, vertex = el.get("chunk"), el.get("vertex")
    if chunk is None or vertex is None or list(vertex.dtype.names) != list(VERTEX_PROPERTIES):
        raise PlyError(f"{path}: not a compressed PLY (needs elements 'chunk' and 'vertex' with {', '.join(VERTEX_PROPERTIES)})")
    n = len(vertex)
    if len(chunk) != -(-n // CHUNK_SIZE):
        raise PlyError(f"{path}: {len(chunk)} chunks for {n} Gaussians; expected {-(-n // CHUNK_SIZE)}")
    missing = [p for p in CHUNK_PROPERTIES[:12] if p not in chunk.dtype.names]
    if missing:
        raise PlyError(f"{path}: chunk element lacks {', '.join(missing)}")
    which = np.arange(n) // CHUNK_SIZE

    def bound(names) -> np.ndarray:
        return np.stack([chunk[p].astype(np.float64) for p in names], 1)[which]

    def lerp(t, lo_names, hi_names):
        lo, hi = bound(lo_names), bound(hi_names)
        return lo * (1 - t) + hi * t

    means = lerp(_unpack_11_10_11(vertex["packed_position"]), ("min_x", "min_y", "min_z"), ("max_x", "max_y", "max_z"))
    log_scales = lerp(_unpack_11_10_11(vertex["packed_scale"]), CHUNK_PROPERTIES[6:9], CHUNK_PROPERTIES[9:12])
    color = vertex["packed_color"]
    rgba = np.stack([(color >> 24) & 0xFF, (color >> 16) & 0xFF, (color >> 8) & 0xFF, color & 0xFF], -1) / 255.0
    rgb = rgba[:, :3]
    if "min_r" in chunk.dtype.names:
        rgb = lerp(rgb, CHUNK_PROPERTIES[12:15], CHUNK_PROPERTIES[15:18])
    rest = _empty_rest(n)
    sh = el.get("sh")
    if sh is not None:
        n_rest = len(sh.dtype.names)
        if n_rest not in (9, 24, 45) or len(sh) != n:
            raise PlyError(f"{path}: sh element has {n_rest} properties for {len(sh)} rows; expected 9, 24 or 45 for {n}")
        q = np.stack([sh[f"f_rest_{i}"] for i in range(n_rest)], 1).astype(np.float64)
        # The middle of each bin; the end bins read as their ends (splat-transform).
        level = np.where(q == 0, 0.0, np.where(q == 255, 1.0, (q + 0.5) / 256.0))
        rest = ((level - 0.5) * 8.0).astype(np.float32).reshape(n, 3, n_rest // 3).transpose(0, 2, 1)
    return PlyGaussians(
        means=means.astype(np.float32),
        sh_dc=((rgb - 0.5) / SH_C0).astype(np.float32),
        sh_rest=np.ascontiguousarray(rest),
        opacity_logits=_alpha_logit(rgba[:, 3]),
        log_scales=log_scales.astype(np.float32),
        quats=unpack_rotations(vertex["packed_rotation"]).astype(np.float32),
    )


# ----- .spz (optional: gsply) --------------------------------------------------------------------
def _gsply():
    try:
        import gsply
    except Exception as e:
        raise ImportError(
            f".spz needs the 'spz' extra (pip install 'gs_regional[spz]', which installs gsply): {e}"
        ) from None
    return gsply


def spz_available() -> bool:
    """Whether .spz can be written here (the 'spz' extra is installed)."""
    try:
        _gsply()
    except ImportError:
        return False
    return True


@contextmanager
def _compiled_gsply() -> Iterator:
    """gsply with its bundled C++ codec where the wheel has one ('auto'): its Numba path compiles
    for seconds on first use. The caller's backend choice is restored afterwards."""
    gsply = _gsply()
    from gsply import _backend

    previous = _backend.selected_backend()
    gsply.use_backend("auto")
    try:
        yield gsply
    finally:
        gsply.use_backend(previous)


def write_spz(path, g: PlyGaussians) -> None:
    """Write `g` as Niantic .spz (version 3, gzip) with gsply (atomically)."""
    path = os.fspath(path)
    _check_not_empty(path, g)
    with _compiled_gsply() as gsply, atomic_write(path) as tmp:
        data = gsply.GSData(
            means=g.means.astype(np.float32), scales=g.log_scales.astype(np.float32),
            quats=_unit_quats(g.quats).astype(np.float32), opacities=g.opacity_logits.astype(np.float32),
            sh0=g.sh_dc.astype(np.float32), shN=g.sh_rest.astype(np.float32),
        )
        gsply.write_spz(tmp, data)


def read_spz(path) -> PlyGaussians:
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise PlyError(f"{path}: file not found")
    with _compiled_gsply() as gsply:
        d = gsply.read_spz(path)
    n = d.means.shape[0]
    rest = np.asarray(d.shN, dtype=np.float32).reshape(n, -1, 3) if d.shN is not None else _empty_rest(n)
    return PlyGaussians(
        means=np.asarray(d.means, dtype=np.float32), sh_dc=np.asarray(d.sh0, dtype=np.float32),
        sh_rest=np.ascontiguousarray(rest), opacity_logits=np.asarray(d.opacities, dtype=np.float32).reshape(n),
        log_scales=np.asarray(d.scales, dtype=np.float32), quats=np.asarray(d.quats, dtype=np.float32),
    )


# ----- all formats -------------------------------------------------------------------------------
# name -> (file suffix, writer, reader)
FORMATS: Dict[str, Tuple[str, Callable, Callable]] = {
    "ply": (".ply", write_ply, read_ply),
    "splat": (".splat", write_splat, read_splat),
    "compressed_ply": (".compressed.ply", write_compressed_ply, read_compressed_ply),
    "spz": (".spz", write_spz, read_spz),
}


def read_scene(path) -> PlyGaussians:
    """Read a scene in any of FORMATS, chosen by the file name (`*.compressed.ply` or a PLY with a
    `chunk` element is a compressed PLY)."""
    name = os.fspath(path).lower()
    if name.endswith(".splat"):
        return read_splat(path)
    if name.endswith(".spz"):
        return read_spz(path)
    if name.endswith(".compressed.ply"):
        return read_compressed_ply(path)
    with open(path, "rb") as f:
        head = f.read(4096)
    if b"\nelement chunk " in head:
        return read_compressed_ply(path)
    return read_ply(path)


@dataclass
class ExportConfig:
    """`system.export`: the files written beside the INRIA PLY (`<stem>.ply`)."""

    splat: bool = True  # <stem>.splat (antimatter15 layout, 32 bytes per Gaussian)
    compressed_ply: bool = True  # <stem>.compressed.ply (SuperSplat / PlayCanvas)
    spz: bool = False  # <stem>.spz (Niantic); needs the 'spz' extra (gsply)
    region: bool = False  # also the edited region alone: <stem>_region.ply and its formats (`--export region`)

    def formats(self) -> List[str]:
        return [name for name in ("splat", "compressed_ply", "spz") if getattr(self, name)]

    def check(self, where: str = "system.export") -> None:
        """Fail at start-up, not after the edit, if a format cannot be written here."""
        if self.spz and not spz_available():
            raise ConfigError(f"{where}.spz=true needs the 'spz' extra: pip install 'gs_regional[spz]' (gsply)")


def export_scene(g: PlyGaussians, stem, formats: List[str]) -> List[Path]:
    """Write `g` as `<stem><suffix>` for each of `formats` (names of FORMATS); returns the paths."""
    paths = []
    for name in formats:
        suffix, write, _ = FORMATS[name]
        path = Path(f"{os.fspath(stem)}{suffix}")
        write(path, g)
        paths.append(path)
    return paths
