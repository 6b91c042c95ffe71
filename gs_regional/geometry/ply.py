"""Read and write 3D Gaussian Splatting scenes in the INRIA PLY layout.

One `vertex` element, one row per Gaussian, float32, binary little endian, properties in order:

  x y z  nx ny nz  f_dc_0..2  f_rest_0..f_rest_{3(K-1)-1}  opacity  scale_0..2  rot_0..3

with K = (D+1)^2 SH coefficients for degree D. `f_rest` is channel-major: all coefficients of
red, then green, then blue, so f_rest index = c*(K-1) + k for channel c and coefficient k+1.
`opacity` is the logit, `scale_*` the log-scales, `rot_*` the quaternion (w, x, y, z).

Any other vertex properties ("extras", e.g. colours or labels some tools add) are read, kept
per Gaussian and written back after the standard ones with their original types.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from gs_regional.utils.io import atomic_write

SH_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # number of f_rest_* properties -> SH degree


class PlyError(ValueError):
    """A PLY file that cannot be used as a Gaussian scene; the message names the file."""


def standard_property_names(sh_degree: int) -> List[str]:
    """The INRIA vertex property names, in file order, for an SH degree."""
    k = (sh_degree + 1) ** 2
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * (k - 1))]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


_NORMALS = ("nx", "ny", "nz")
# Required properties apart from f_rest (whose count decides the degree); normals are optional.
_REQUIRED = [n for n in standard_property_names(0) if n not in _NORMALS]


@dataclass
class PlyGaussians:
    """The contents of a 3DGS PLY as numpy arrays (N Gaussians, K SH coefficients)."""

    means: np.ndarray  # (N, 3) float32
    sh_dc: np.ndarray  # (N, 3)
    sh_rest: np.ndarray  # (N, K-1, 3)  [coefficient, channel]
    opacity_logits: np.ndarray  # (N,)
    log_scales: np.ndarray  # (N, 3)
    quats: np.ndarray  # (N, 4) w, x, y, z
    normals: Optional[np.ndarray] = None  # (N, 3); None -> written as zeros
    extras: Dict[str, np.ndarray] = field(default_factory=dict)  # name -> (N,), file order

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        k_minus_1 = self.sh_rest.shape[1]
        degree = {0: 0, 3: 1, 8: 2, 15: 3}.get(k_minus_1)
        if degree is None:
            raise PlyError(f"sh_rest has {k_minus_1} coefficients per channel; expected 0, 3, 8 or 15")
        return degree


def _check_file(path: str) -> None:
    if not os.path.exists(path):
        raise PlyError(f"{path}: file not found")
    if os.path.isdir(path):
        raise PlyError(f"{path}: is a directory, not a PLY file")
    if os.path.getsize(path) == 0:
        raise PlyError(f"{path}: empty file (0 bytes), not a PLY file")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic[:3] != b"ply" or magic[3:4] not in (b"\n", b"\r"):
        raise PlyError(f"{path}: not a PLY file (it does not start with the 'ply' magic line)")


def _load_vertex(path: str) -> np.ndarray:
    from plyfile import PlyData

    try:
        with open(path, "rb") as f:
            # Binary elements without list properties are memory-mapped as one structured numpy
            # array (plyfile reads any other element, and ASCII files, row by row in Python:
            # minutes for a million Gaussians). Copy-on-write: the file is never modified.
            ply = PlyData.read(f, mmap="c")
    except Exception as e:  # plyfile's parse errors, truncated data, bad numbers
        raise PlyError(f"{path}: cannot parse PLY: {type(e).__name__}: {e}") from None
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise PlyError(
            f"{path}: no 'vertex' element (elements present: {', '.join(names) or 'none'}); "
            f"a 3DGS PLY stores one vertex per Gaussian"
        )
    others = [n for n in names if n != "vertex"]
    if others:
        warnings.warn(f"{path}: ignoring non-vertex elements {others}", stacklevel=3)
    vertex = ply["vertex"]
    lists = [p.name for p in vertex.properties if hasattr(p, "len_dtype")]
    if lists:
        raise PlyError(f"{path}: list properties on 'vertex' are not supported: {', '.join(lists)}")
    data = vertex.data
    if isinstance(data, np.memmap) and len(data):
        # One read of the mapped block into memory: 10x faster than paging the mapping in
        # (0.04 s for 1M Gaussians instead of 0.4 s), and nothing returned refers to the file.
        rows = np.empty(len(data), dtype=data.dtype)
        with open(path, "rb") as f:
            f.seek(data.offset)
            got = f.readinto(memoryview(rows).cast("B"))
        if got != rows.nbytes:  # the file changed since it was mapped
            raise PlyError(f"{path}: cannot parse PLY: vertex data ends after {got} of {rows.nbytes} bytes")
        data = rows
    return data


def _float32_table(data: np.ndarray) -> Optional[np.ndarray]:
    """(N, P) float32 view of structured rows whose P fields are all packed float32 of one byte
    order (converted to native order when needed), else None."""
    fields = [data.dtype.fields[p] for p in data.dtype.names]
    kinds = {dt.str for dt, _ in fields}
    if len(kinds) != 1 or next(iter(kinds)) not in ("<f4", ">f4"):
        return None
    if data.dtype.itemsize != 4 * len(fields) or [off for _, off in fields] != list(range(0, 4 * len(fields), 4)):
        return None  # padded or reordered layout: no plain (N, P) view
    if not data.flags.c_contiguous:
        return None
    return data.view(fields[0][0]).reshape(len(data), len(fields)).astype(np.float32, copy=False)


def read_ply(path, drop_nonfinite: bool = False) -> PlyGaussians:
    """Read a 3DGS PLY. Every problem raises PlyError naming the file.

    With `drop_nonfinite`, Gaussians holding NaN/inf values are dropped with a warning
    instead of failing.
    """
    path = os.fspath(path)
    check_ply_size(path)  # a truncated file, or bytes the header does not declare
    data = _load_vertex(path)
    n = len(data)
    names = list(data.dtype.names or ())
    if n == 0:
        raise PlyError(f"{path}: the 'vertex' element has 0 vertices: the scene holds no Gaussians")

    missing = [p for p in _REQUIRED if p not in names]
    if missing:
        raise PlyError(f"{path}: missing vertex properties: {', '.join(missing)}")
    rest_names = [p for p in names if p.startswith("f_rest_")]
    if len(rest_names) not in SH_REST_COUNTS:
        raise PlyError(
            f"{path}: has {len(rest_names)} f_rest_* properties; a 3DGS PLY has 0, 9, 24 or 45 "
            f"(SH degree 0, 1, 2 or 3)"
        )
    degree = SH_REST_COUNTS[len(rest_names)]
    standard = standard_property_names(degree)
    missing = [p for p in standard if p.startswith("f_rest_") and p not in names]
    if missing:  # e.g. f_rest_0, f_rest_2, ... with a gap
        raise PlyError(f"{path}: missing vertex properties: {', '.join(missing)}")
    extra_names = [p for p in names if p not in standard]
    for p in extra_names:
        if data.dtype[p].kind not in "biuf":
            raise PlyError(f"{path}: vertex property '{p}' has unsupported type {data.dtype[p]}")

    # All properties float32 (the INRIA layout and most tools): one (N, P) view of the rows, so
    # that every check and column copy below is a vectorised numpy operation.
    table = _float32_table(data)
    column_of = {p: j for j, p in enumerate(names)}

    # Non-finite values: count over every floating property (standard and extra).
    float_names = [p for p in names if data.dtype[p].kind == "f"]
    if table is not None:
        bad = ~np.isfinite(table)
        bad_per_prop = bad.sum(0)
        bad_props = [names[j] for j in np.flatnonzero(bad_per_prop)]
        bad_values = int(bad_per_prop.sum())
        bad_rows = bad.any(1)
        del bad
    else:
        bad_rows = np.zeros(n, dtype=bool)
        bad_props, bad_values = [], 0
        for p in float_names:
            bad = ~np.isfinite(data[p])
            if bad.any():
                bad_props.append(p)
                bad_values += int(bad.sum())
                bad_rows |= bad
    if bad_rows.any():
        what = (
            f"{int(bad_rows.sum())} of {n} Gaussians have NaN/inf values ({bad_values} values, "
            f"in properties: {', '.join(bad_props)})"
        )
        if not drop_nonfinite:
            raise PlyError(f"{path}: {what}; pass drop_nonfinite=True to drop those Gaussians")
        if bad_rows.all():
            raise PlyError(f"{path}: {what}; no Gaussians would remain")
        warnings.warn(f"{path}: {what}; dropping them", stacklevel=2)
        data = data[~bad_rows]
        table = None if table is None else table[~bad_rows]
        n = len(data)

    def cols(props: List[str]) -> np.ndarray:
        if table is not None:
            # take, not table[:, list]: numpy's fancy indexing along columns is ~10x slower
            return table.take([column_of[p] for p in props], axis=1)
        return np.stack([np.asarray(data[p], dtype=np.float32) for p in props], axis=1)

    k1 = (degree + 1) ** 2 - 1
    if k1:
        # channel-major in the file: (N, 3, K-1) -> (N, K-1, 3)
        rest = cols([f"f_rest_{i}" for i in range(3 * k1)]).reshape(n, 3, k1).transpose(0, 2, 1)
    else:
        rest = np.zeros((n, 0, 3), dtype=np.float32)
    normals = None
    if any(p in names for p in _NORMALS):  # a missing component counts as 0
        normals = np.stack(
            [np.asarray(data[p], dtype=np.float32) if p in names else np.zeros(n, np.float32) for p in _NORMALS],
            axis=1,
        )
        if not normals.any():
            normals = None  # INRIA files store zeros; nothing to keep
    return PlyGaussians(
        means=cols(["x", "y", "z"]),
        sh_dc=cols(["f_dc_0", "f_dc_1", "f_dc_2"]),
        sh_rest=np.ascontiguousarray(rest),
        opacity_logits=np.asarray(data["opacity"], dtype=np.float32).copy(),
        log_scales=cols(["scale_0", "scale_1", "scale_2"]),
        quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]),
        normals=normals,
        extras={p: np.asarray(data[p]).copy() for p in extra_names},
    )


def write_ply(path, g: PlyGaussians) -> None:
    """Write `g` atomically in the INRIA layout (float32, binary little endian), extras last."""
    from plyfile import PlyData, PlyElement

    path = os.fspath(path)
    n = g.num_gaussians
    degree = g.sh_degree
    k1 = (degree + 1) ** 2 - 1
    shapes = {
        "means": (g.means, (n, 3)),
        "sh_dc": (g.sh_dc, (n, 3)),
        "sh_rest": (g.sh_rest, (n, k1, 3)),
        "opacity_logits": (g.opacity_logits, (n,)),
        "log_scales": (g.log_scales, (n, 3)),
        "quats": (g.quats, (n, 4)),
    }
    if g.normals is not None:
        shapes["normals"] = (g.normals, (n, 3))
    for name, (arr, shape) in shapes.items():
        if tuple(arr.shape) != shape:
            raise PlyError(f"{path}: cannot write: {name} has shape {tuple(arr.shape)}, expected {shape}")
    for name, arr in g.extras.items():
        if tuple(arr.shape) != (n,):
            raise PlyError(f"{path}: cannot write: extra property '{name}' has shape {tuple(arr.shape)}, expected ({n},)")
    standard = standard_property_names(degree)
    clash = [p for p in g.extras if p in standard]
    if clash:
        raise PlyError(f"{path}: cannot write: extra properties clash with standard ones: {clash}")

    # The standard properties as one (N, P) float32 array, filled in place (no concatenation).
    columns = np.empty((n, len(standard)), dtype="<f4")
    columns[:, 0:3] = g.means
    columns[:, 3:6] = 0.0 if g.normals is None else g.normals
    columns[:, 6:9] = g.sh_dc
    # channel-major f_rest; the reshape of the column block is a view (its strides allow it)
    columns[:, 9 : 9 + 3 * k1].reshape(n, 3, k1)[:] = np.asarray(g.sh_rest).transpose(0, 2, 1)
    columns[:, 9 + 3 * k1] = g.opacity_logits
    columns[:, -7:-4] = g.log_scales
    columns[:, -4:] = g.quats
    dtype = [(p, "<f4") for p in standard]
    dtype += [(p, np.dtype(a.dtype).newbyteorder("<").str) for p, a in g.extras.items()]
    if g.extras:
        rows = np.empty(n, dtype=dtype)
        for i, p in enumerate(standard):
            rows[p] = columns[:, i]
        for p, a in g.extras.items():
            rows[p] = a
    else:  # all float32: the (N, P) array already is the rows' bytes
        rows = columns.view(np.dtype(dtype))[:, 0]
    element = PlyElement.describe(rows, "vertex")
    with atomic_write(path) as tmp:
        PlyData([element], text=False, byte_order="<").write(tmp)


_PLY_TYPE_BYTES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}


@dataclass
class PlyHeader:
    """What a PLY header declares: its format, its elements as (name, count, [(property, type)])
    (a list property's type is "list"), and the header's own size in bytes."""

    format: str
    elements: List[tuple]
    header_bytes: int

    def data_bytes(self) -> Optional[int]:
        """Bytes of the data the header declares, or None when it cannot be known from the header
        alone (ASCII, or list properties)."""
        if not self.format.startswith("binary"):
            return None
        total = 0
        for _, count, props in self.elements:
            if any(t not in _PLY_TYPE_BYTES for _, t in props):
                return None
            total += count * sum(_PLY_TYPE_BYTES[t] for _, t in props)
        return total


def read_ply_header(path) -> PlyHeader:
    """Parse the header of the PLY at `path` (at most 64 KiB are read); PlyError names the file."""
    path = os.fspath(path)
    _check_file(path)
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    for marker in (b"end_header\n", b"end_header\r\n"):
        if marker in head:
            end = head.index(marker) + len(marker)
            break
    else:
        raise PlyError(f"{path}: not a PLY file with a header under 64 KiB (no end_header line)")
    fmt, elements = "", []
    try:
        for line in head[:end].decode("ascii").splitlines():
            words = line.split()
            if words[:1] == ["format"]:
                fmt = words[1]
            elif words[:1] == ["element"]:
                elements.append((words[1], int(words[2]), []))
            elif words[:1] == ["property"]:
                if not elements:
                    raise ValueError(f"property before any element: {line!r}")
                elements[-1][2].append((words[-1], "list" if words[1] == "list" else words[1]))
    except (UnicodeDecodeError, ValueError, IndexError) as e:
        raise PlyError(f"{path}: cannot parse PLY header: {e}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path}: cannot parse PLY header: unknown format {fmt!r}")
    return PlyHeader(fmt, elements, end)


def check_ply_size(path, header: Optional[PlyHeader] = None) -> None:
    """Compare the file's size with what its header declares: fewer bytes is a truncated file
    (PlyError); more bytes are data that no reader will see (a warning with the byte count)."""
    path = os.fspath(path)
    header = header or read_ply_header(path)
    declared = header.data_bytes()
    if declared is None:
        return
    actual = os.path.getsize(path) - header.header_bytes
    counts = ", ".join(f"{count:,} {name}" for name, count, _ in header.elements)
    if actual < declared:
        raise PlyError(f"{path}: cannot parse PLY: truncated: the header declares {counts} ({declared:,} bytes of data) but the file "
                       f"holds {actual:,} bytes after the header")
    if actual > declared:
        warnings.warn(f"{path}: the header declares {counts} ({declared:,} bytes of data) but the file holds "
                      f"{actual - declared:,} more bytes after them; they are ignored (a header whose vertex count "
                      "is too small?)", stacklevel=2)


def check_ply_header(path) -> PlyHeader:
    """A fast check of a 3DGS PLY before anything is loaded: the header parses, declares a
    non-empty `vertex` element with the required properties, and the file's size matches it."""
    path = os.fspath(path)
    header = read_ply_header(path)
    vertex = next((e for e in header.elements if e[0] == "vertex"), None)
    if vertex is None:
        names = ", ".join(e[0] for e in header.elements) or "none"
        raise PlyError(f"{path}: no 'vertex' element (elements present: {names}); a 3DGS PLY stores one vertex "
                       "per Gaussian")
    if vertex[1] == 0:
        raise PlyError(f"{path}: the 'vertex' element has 0 vertices: the scene holds no Gaussians")
    props = {name for name, _ in vertex[2]}
    missing = [p for p in _REQUIRED if p not in props]
    if missing:
        raise PlyError(f"{path}: missing vertex properties: {', '.join(missing)}")
    check_ply_size(path, header)
    return header


def ply_bytes_with_rows(path, rows: int) -> int:
    """The size in bytes of the binary PLY at `path` (one `vertex` element of scalar properties,
    as `write_ply` writes it) if it held `rows` Gaussians instead of its own: exact, without
    writing it (e.g. the source scene's size in the layout of an edited scene's file)."""
    path = os.fspath(path)
    header = read_ply_header(path)
    if len(header.elements) != 1 or header.elements[0][0] != "vertex" or not header.format.startswith("binary"):
        raise PlyError(f"{path}: expected one binary 'vertex' element")
    _, count, props = header.elements[0]
    bad = [t for _, t in props if t not in _PLY_TYPE_BYTES]
    if bad:
        raise PlyError(f"{path}: property type '{bad[0]}' is not a scalar PLY type")
    row_bytes = sum(_PLY_TYPE_BYTES[t] for _, t in props)
    return header.header_bytes - len(str(count)) + len(str(int(rows))) + int(rows) * row_bytes
