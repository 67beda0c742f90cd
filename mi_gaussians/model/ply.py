"""3DGS ``point_cloud.ply`` reading and writing: the only place the 3DGS attribute names and their order live.

File layout written (identical to the reference implementation, which SIBR, SuperSplat, gsplat and Mitsuba's
``ellipsoids`` shape read)::

    ply
    format binary_little_endian 1.0
    element vertex N
    property float x            (then y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1}
    ...                          opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3, one line each)
    end_header
    <N records of float32 little-endian, raw (pre-activation) values, normals zero>

``f_rest`` is channel-major (all R coefficients of bands 1.., then G, then B); in memory we keep the coefficient-major
``(N, K - 1, 3)`` layout of :class:`mi_gaussians.model.gaussians.Gaussians` (see :mod:`mi_gaussians.conventions`).

Reading accepts files by other tools: properties in any order, extra properties ignored (normals are optional),
``float``/``float32``/``double``/``float64``/``half`` for the Gaussian attributes, any PLY scalar type for the
ignored ones, other elements before or after ``vertex``, ``binary_little_endian``, ``binary_big_endian`` and ``ascii``
formats, ``\\n`` or ``\\r\\n`` header lines. The SH degree (0..3) follows from the number of ``f_rest_*`` properties
(0, 9, 24, 45). Every problem raises :class:`PLYError` (a ``ValueError``) with a one-line message that starts with
the file's path.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..conventions import (MAX_ABS_SH_COEFFICIENT, sh_channel_major_to_coeff_major, sh_coeff_count,
                           sh_coeff_major_to_channel_major)
from ..io_utils import atomic_path

#: PLY scalar type names -> NumPy type codes (the official names and the common sized aliases).
PLY_SCALAR_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "long": "i8", "int64": "i8", "ulong": "u8", "uint64": "u8",
    "half": "f2", "float16": "f2", "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "="}

#: Number of ``f_rest_*`` properties for SH degrees 0..3: 3 (K - 1), i.e. 0, 9, 24, 45.
F_REST_COUNTS = {d: 3 * (sh_coeff_count(d) - 1) for d in range(4)}
_DEGREE_OF_F_REST = {m: d for d, m in F_REST_COUNTS.items()}

_MAX_HEADER_BYTES = 1 << 20
_MAX_LINE_BYTES = 1 << 16


class PLYError(ValueError):
    """A PLY file that cannot be read or written as 3DGS Gaussians. ``str(e)`` is one line: ``"<path>: <problem>"``."""
    def __init__(self, path, problem: str):
        self.path = os.fspath(path)
        self.problem = " ".join(str(problem).split())
        super().__init__(f"{self.path}: {self.problem}")


# ---------------------------------------------------------------------------------------------------- names
def ply_property_names(sh_degree: int) -> list[str]:
    """The vertex property names, in file order, of a 3DGS PLY with SH degree ``sh_degree`` (0..3)."""
    if sh_degree not in F_REST_COUNTS:
        raise ValueError(f"SH degree must be 0..3, got {sh_degree!r}")
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(F_REST_COUNTS[sh_degree])]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


_GROUPS = {  # output key -> PLY property names (f_rest handled separately)
    "means": ("x", "y", "z"),
    "sh_dc": ("f_dc_0", "f_dc_1", "f_dc_2"),
    "opacities": ("opacity",),
    "scales": ("scale_0", "scale_1", "scale_2"),
    "rotations": ("rot_0", "rot_1", "rot_2", "rot_3"),
}


# ---------------------------------------------------------------------------------------------------- header
@dataclass(frozen=True)
class PlyProperty:
    """One property of a PLY element. ``dtype`` is a NumPy type code without byte order (``'f4'``); list properties
    have ``count_dtype`` set (the type of the length prefix) and ``dtype`` is the item type."""

    name: str
    dtype: str
    count_dtype: str | None = None

    @property
    def is_list(self) -> bool:
        return self.count_dtype is not None


@dataclass(frozen=True)
class PlyElement:
    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    @property
    def has_lists(self) -> bool:
        return any(p.is_list for p in self.properties)

    def record_dtype(self, byte_order: str) -> np.dtype:
        """Packed structured dtype of one record (scalar properties only)."""
        return np.dtype([(p.name, byte_order + p.dtype) for p in self.properties])


@dataclass(frozen=True)
class PlyHeader:
    """A parsed PLY header. ``data_offset`` is the byte offset of the first data byte after ``end_header``."""

    format: str
    elements: tuple[PlyElement, ...]
    comments: tuple[str, ...]
    data_offset: int

    @property
    def byte_order(self) -> str:
        return _FORMATS[self.format]

    def element(self, name: str) -> PlyElement | None:
        for el in self.elements:
            if el.name == name:
                return el
        return None


def _short(s: str, limit: int = 60) -> str:
    """``repr(s)``, cut to about ``limit`` characters for error messages."""
    r = repr(s)
    return r if len(r) <= limit else r[: limit - 4] + "...'"


def _parse_header(f, path) -> PlyHeader:
    first = f.readline(_MAX_LINE_BYTES)
    if not first:
        raise PLYError(path, "not a PLY file (the file is empty)")
    if first.rstrip(b"\r\n") != b"ply":
        raise PLYError(path, "not a PLY file (it does not start with a 'ply' line)")
    fmt = None
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    comments: list[str] = []
    lineno = 1
    total = len(first)
    while True:
        raw = f.readline(_MAX_LINE_BYTES)
        lineno += 1
        total += len(raw)
        if not raw or total > _MAX_HEADER_BYTES:
            raise PLYError(path, "invalid PLY header: no 'end_header' line")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            if not raw.startswith((b"comment", b"obj_info")):  # non-ASCII comments (UTF-8) are tolerated
                raise PLYError(path, f"invalid PLY header: line {lineno} is not ASCII text "
                                     "(binary data before 'end_header'?)") from None
            line = raw.decode("utf-8", errors="replace").strip()
        if any(c < " " and c != "\t" for c in line) or "\x7f" in line:
            raise PLYError(path, f"invalid PLY header: line {lineno} holds control characters "
                                 "(binary data before 'end_header'?)")
        tok = line.split()
        if not tok:
            continue
        key = tok[0]
        if key in ("comment", "obj_info"):
            comments.append(line[len(key):].strip())
        elif key == "format":
            if fmt is not None:
                raise PLYError(path, f"invalid PLY header: duplicate 'format' line {lineno}")
            if len(tok) < 2 or tok[1] not in _FORMATS:
                raise PLYError(path, f"unsupported PLY format {_short(line)} (expected binary_little_endian, "
                                     "binary_big_endian or ascii)")
            fmt = tok[1]
        elif key == "element":
            if len(tok) != 3:
                raise PLYError(path, f"invalid PLY header line {lineno}: {_short(line)}")
            try:
                count = int(tok[2])
            except ValueError:
                count = -1
            if count < 0:
                raise PLYError(path, f"invalid element count {tok[2]!r} for element {tok[1]!r}")
            elements.append((tok[1], count, []))
        elif key == "property":
            if not elements:
                raise PLYError(path, f"invalid PLY header: property before any element on line {lineno}")
            if len(tok) == 5 and tok[1] == "list":
                ct, it, name = tok[2], tok[3], tok[4]
                for t in (ct, it):
                    if t not in PLY_SCALAR_TYPES:
                        raise PLYError(path, f"unsupported PLY type {t!r} for list property {name!r}")
                prop = PlyProperty(name, PLY_SCALAR_TYPES[it], PLY_SCALAR_TYPES[ct])
            elif len(tok) == 3:
                if tok[1] not in PLY_SCALAR_TYPES:
                    raise PLYError(path, f"unsupported PLY type {tok[1]!r} for property {tok[2]!r}")
                prop = PlyProperty(tok[2], PLY_SCALAR_TYPES[tok[1]])
            else:
                raise PLYError(path, f"invalid PLY header line {lineno}: {_short(line)}")
            elements[-1][2].append(prop)
        elif key == "end_header":
            break
        else:
            raise PLYError(path, f"invalid PLY header: unknown keyword {_short(key)} on line {lineno}")
    if fmt is None:
        raise PLYError(path, "invalid PLY header: no 'format' line")
    return PlyHeader(fmt, tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements), tuple(comments), f.tell())


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """Parse only the header of a PLY file (any PLY, not necessarily 3DGS)."""
    try:
        with open(path, "rb") as f:
            return _parse_header(f, path)
    except OSError as e:
        raise PLYError(path, f"cannot read file: {e.strerror or e}") from None


# ---------------------------------------------------------------------------------------------------- reading
def _vertex_layout(header: PlyHeader, path) -> tuple[PlyElement, dict[str, list[str]], int]:
    """Validate the vertex element; return it, the PLY names per output key and the SH degree."""
    vertex = header.element("vertex")
    if vertex is None:
        names = ", ".join(repr(e.name) for e in header.elements) or "none"
        raise PLYError(path, f"no 'vertex' element (elements: {names})")
    names = [p.name for p in vertex.properties]
    seen, dups = set(), []
    for n in names:
        if n in seen and n not in dups:
            dups.append(n)
        seen.add(n)
    if dups:
        raise PLYError(path, "duplicate vertex properties: " + ", ".join(repr(n) for n in dups))
    if "packed_position" in seen:
        raise PLYError(path, "compressed PLY (packed_* properties, SuperSplat/PlayCanvas format) is not supported; "
                             "export or decompress it to a standard 3DGS PLY first")
    wanted = [n for group in _GROUPS.values() for n in group]
    missing = [n for n in wanted if n not in seen]
    if missing:
        raise PLYError(path, "missing vertex properties: " + ", ".join(repr(n) for n in missing))
    rest = [n for n in names if n.startswith("f_rest_")]
    m = len(rest)
    if m not in _DEGREE_OF_F_REST:
        raise PLYError(path, f"{m} f_rest properties: expected 0, 9, 24 or 45 (SH degree 0..3)")
    expected_rest = [f"f_rest_{i}" for i in range(m)]
    if set(rest) != set(expected_rest):
        odd = sorted(set(rest) - set(expected_rest))
        raise PLYError(path, f"f_rest properties are not numbered f_rest_0..f_rest_{m - 1} "
                             f"(unexpected: {', '.join(repr(n) for n in odd[:5])})")
    by_name = {p.name: p for p in vertex.properties}
    for n in wanted + expected_rest:
        p = by_name[n]
        if p.is_list:
            raise PLYError(path, f"vertex property {n!r} is a list; expected a float scalar")
        if p.dtype[0] != "f":
            ply_type = next(k for k, v in PLY_SCALAR_TYPES.items() if v == p.dtype)
            raise PLYError(path, f"vertex property {n!r} has integer type {ply_type!r}; expected float or double")
    groups = dict(_GROUPS)
    groups["f_rest"] = tuple(expected_rest)
    return vertex, groups, _DEGREE_OF_F_REST[m]


def read_vertices(path: str | os.PathLike) -> tuple[PlyElement, np.ndarray]:
    """The ``vertex`` element of any PLY file (binary or ascii) and its records (a structured array, every scalar
    property by name): for other kinds of PLY than 3DGS models, e.g. point clouds. PLYError naming the file."""
    try:
        with open(path, "rb") as f:
            header = _parse_header(f, path)
            if (vertex := header.element("vertex")) is None:
                raise PLYError(path, "no 'vertex' element")
            return vertex, (_read_ascii_vertices(f, header, vertex, path) if header.format == "ascii" else
                            _read_binary_vertices(f, header, vertex, path, os.fstat(f.fileno()).st_size))
    except OSError as e:
        raise PLYError(path, f"cannot read file: {e.strerror or e}") from None


def _read_binary_vertices(f, header: PlyHeader, vertex: PlyElement, path, file_size: int) -> np.ndarray:
    bo = header.byte_order
    offset = header.data_offset
    idx = header.elements.index(vertex)
    for el in header.elements[:idx]:
        if el.has_lists:
            raise PLYError(path, f"element {el.name!r} with list properties before 'vertex' is not supported "
                                 "in binary PLY files")
        offset += el.count * el.record_dtype(bo).itemsize
    if vertex.has_lists:
        raise PLYError(path, "the 'vertex' element has list properties; expected scalar properties only")
    dtype = vertex.record_dtype(bo)
    need = vertex.count * dtype.itemsize
    have = max(file_size - offset, 0)
    if have < need:
        raise PLYError(path, f"truncated file: {vertex.count} vertices of {dtype.itemsize} bytes need {need} bytes "
                             f"but only {have} follow (vertex count wrong or file cut short)")
    if idx == len(header.elements) - 1 and have != need:
        raise PLYError(path, f"vertex count mismatch: {vertex.count} vertices of {dtype.itemsize} bytes need {need} "
                             f"bytes but {have} follow the header")
    f.seek(offset)
    buf = f.read(need)
    if len(buf) != need:
        raise PLYError(path, f"truncated file: could only read {len(buf)} of {need} bytes of vertex data")
    return np.frombuffer(buf, dtype=dtype, count=vertex.count)


def _read_ascii_vertices(f, header: PlyHeader, vertex: PlyElement, path) -> np.ndarray:
    f.seek(header.data_offset)
    try:
        tokens = f.read().decode("ascii").split()
    except UnicodeDecodeError:
        raise PLYError(path, "ascii PLY data is not ASCII text") from None
    pos = 0
    idx = header.elements.index(vertex)
    for el in header.elements[:idx]:
        if not el.has_lists:
            pos += el.count * len(el.properties)
            continue
        for _ in range(el.count):
            for p in el.properties:
                if p.is_list:
                    try:
                        pos += 1 + int(tokens[pos])
                    except (IndexError, ValueError):
                        raise PLYError(path, f"invalid list length in ascii element {el.name!r}") from None
                else:
                    pos += 1
    if vertex.has_lists:
        raise PLYError(path, "the 'vertex' element has list properties; expected scalar properties only")
    nprop = len(vertex.properties)
    need = vertex.count * nprop
    have = max(len(tokens) - pos, 0)
    if have < need:
        raise PLYError(path, f"truncated file: {vertex.count} vertices need {need} ascii values but only {have} follow"
                             " (vertex count wrong or file cut short)")
    if idx == len(header.elements) - 1 and have != need:
        raise PLYError(path, f"vertex count mismatch: {vertex.count} vertices need {need} ascii values but {have} "
                             "follow the header")
    table = np.asarray(tokens[pos:pos + need], dtype=str).reshape(vertex.count, nprop)
    out = np.empty(vertex.count, dtype=vertex.record_dtype("="))
    for j, p in enumerate(vertex.properties):
        try:
            out[p.name] = table[:, j].astype(np.float64 if p.dtype[0] == "f" else np.int64)
        except (ValueError, OverflowError):
            raise PLYError(path, f"invalid ascii value in vertex property {p.name!r}") from None
    return out


def _check_colour_range(path, cols: dict, groups: dict) -> None:
    """Refuse colour coefficients beyond ``MAX_ABS_SH_COEFFICIENT`` (they render Inf pixels), naming the property."""
    for key in ("sh_dc", "f_rest"):
        a = np.abs(cols[key])
        big = a > MAX_ABS_SH_COEFFICIENT      # (NaN compares False: non-finite values are the caller's choice)
        if not big.any():
            continue
        over = np.where(big, a, 0.0).max(axis=0)
        j = int(np.argmax(over))
        count = int(big.sum())
        raise PLYError(path, f"{count} colour coefficient{'s' if count > 1 else ''} beyond +-{MAX_ABS_SH_COEFFICIENT:g} "
                             f"(largest {over[j]:g} in {groups[key][j]!r}); colours that large render as Inf")


def read_ply(path: str | os.PathLike, *, allow_nonfinite: bool = False,
             renderable: bool = False) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY into raw float32 arrays, keyed like ``Gaussians.from_numpy``.

    Returns ``means`` (N, 3), ``scales`` (N, 3), ``rotations`` (N, 4) wxyz, ``opacities`` (N,), ``sh_dc`` (N, 3),
    ``sh_rest`` (N, K - 1, 3) coefficient-major, all C-contiguous float32. For float32 files the values are the
    file's bits exactly; ``double``/``half`` properties are rounded to float32.

    Raises :class:`PLYError` (one line, starting with the path) for: not a PLY file, unsupported format or type,
    no ``vertex`` element, a missing attribute (named), an ``f_rest`` count other than 0/9/24/45, a truncated file or
    a vertex count that does not match the data, and -- unless ``allow_nonfinite`` -- NaN or Inf values (per
    attribute, with counts); with ``renderable`` (as :meth:`Gaussians.load_ply` asks) also colour coefficients beyond
    ``MAX_ABS_SH_COEFFICIENT``, which render Inf pixels. Without it every finite float32 is read bit for bit."""
    try:
        with open(path, "rb") as f:
            header = _parse_header(f, path)
            vertex, groups, degree = _vertex_layout(header, path)
            if header.format == "ascii":
                rec = _read_ascii_vertices(f, header, vertex, path)
            else:
                rec = _read_binary_vertices(f, header, vertex, path, os.fstat(f.fileno()).st_size)
    except OSError as e:
        raise PLYError(path, f"cannot read file: {e.strerror or e}") from None

    n = vertex.count
    cols = {}
    fields = [rec.dtype.fields[p.name][0] for p in vertex.properties]
    if all(f == np.dtype("<f4") for f in fields) and rec.dtype.itemsize == 4 * len(fields):
        # fast path (every file we write): one float32 matrix, columns picked by index -- a bit-exact copy
        mat = rec.view(np.dtype("<f4")).reshape(n, len(fields))
        pos = {p.name: i for i, p in enumerate(vertex.properties)}
        for key, props in groups.items():
            cols[key] = np.ascontiguousarray(mat[:, [pos[name] for name in props]], dtype=np.float32)
    else:
        with np.errstate(over="ignore", under="ignore"):
            for key, props in groups.items():
                a = np.empty((n, len(props)), np.float32)
                for j, name in enumerate(props):
                    a[:, j] = rec[name]
                cols[key] = a

    if not allow_nonfinite:
        problems = []
        for key, props in groups.items():
            a = cols[key]
            finite = np.isfinite(a)
            if finite.all():
                continue
            for j, name in enumerate(props):
                nan = int(np.isnan(a[:, j]).sum())
                inf = int((~finite[:, j]).sum()) - nan
                parts = ([f"{nan} NaN"] if nan else []) + ([f"{inf} Inf"] if inf else [])
                if parts:
                    problems.append(f"{' and '.join(parts)} in {name!r}")
        if problems:
            shown = problems[:6] + ([f"... ({len(problems) - 6} more properties)"] if len(problems) > 6 else [])
            raise PLYError(path, "non-finite values (after conversion to float32): " + ", ".join(shown))
    if renderable:
        _check_colour_range(path, cols, groups)

    return {
        "means": cols["means"],
        "scales": cols["scales"],
        "rotations": cols["rotations"],
        "opacities": np.ascontiguousarray(cols["opacities"][:, 0]),
        "sh_dc": cols["sh_dc"],
        "sh_rest": sh_channel_major_to_coeff_major(cols["f_rest"]),
    }


# ---------------------------------------------------------------------------------------------------- writing
def _as_f32(path, name: str, a, shape: tuple) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float32)
    except (TypeError, ValueError) as e:
        raise PLYError(path, f"cannot write {name}: {e}") from None
    if arr.shape != shape:
        raise PLYError(path, f"cannot write {name}: expected shape {shape}, got {arr.shape}")
    return arr


def write_ply(path: str | os.PathLike, means, scales, rotations, opacities, sh_dc, sh_rest=None, *,
              check_finite: bool = True) -> None:
    """Write raw Gaussian parameters as a reference-layout 3DGS PLY, atomically (temporary file + rename).

    means (N, 3), scales (N, 3) log-sigma, rotations (N, 4) wxyz, opacities (N,) logits, sh_dc (N, 3),
    sh_rest (N, K - 1, 3) coefficient-major with K - 1 in {0, 3, 8, 15} (None: degree 0). Values are converted to
    float32 (bit-exact for float32 input) and written unchanged; normals are zero. With ``check_finite`` (default) NaN or
    Inf values raise :class:`PLYError` and nothing is written, so every file we write can be read back."""
    means = np.asarray(means)
    if means.ndim != 2 or means.shape[1] != 3:
        raise PLYError(path, f"cannot write means: expected shape (N, 3), got {means.shape}")
    n = means.shape[0]
    arrays = {
        "means": _as_f32(path, "means", means, (n, 3)),
        "sh_dc": _as_f32(path, "sh_dc", sh_dc, (n, 3)),
        "opacities": _as_f32(path, "opacities", opacities, (n,)),
        "scales": _as_f32(path, "scales", scales, (n, 3)),
        "rotations": _as_f32(path, "rotations", rotations, (n, 4)),
    }
    if sh_rest is None:
        rest = np.zeros((n, 0, 3), np.float32)
    else:
        rest = np.asarray(sh_rest, dtype=np.float32)
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3 or 3 * rest.shape[1] not in _DEGREE_OF_F_REST:
            raise PLYError(path, f"cannot write sh_rest: expected shape ({n}, K - 1, 3) with K - 1 in 0, 3, 8, 15, "
                                 f"got {rest.shape}")
    degree = _DEGREE_OF_F_REST[3 * rest.shape[1]]
    arrays["sh_rest"] = rest
    if check_finite:
        bad = [f"{int((~np.isfinite(a)).sum())} in {k}" for k, a in arrays.items() if not np.isfinite(a).all()]
        if bad:
            raise PLYError(path, "refusing to write non-finite values: " + ", ".join(bad))

    names = ply_property_names(degree)
    table = np.empty((n, len(names)), dtype="<f4")
    table[:, 0:3] = arrays["means"]
    table[:, 3:6] = 0.0
    table[:, 6:9] = arrays["sh_dc"]
    m = F_REST_COUNTS[degree]
    table[:, 9:9 + m] = sh_coeff_major_to_channel_major(rest)
    table[:, 9 + m] = arrays["opacities"]
    table[:, 10 + m:13 + m] = arrays["scales"]
    table[:, 13 + m:17 + m] = arrays["rotations"]

    header = "".join(["ply\n", "format binary_little_endian 1.0\n", f"element vertex {n}\n"]
                     + [f"property float {name}\n" for name in names] + ["end_header\n"])
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(table.tobytes())
            f.flush()
            os.fsync(f.fileno())


def convert_ply(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Rewrite any 3DGS PLY that :func:`read_ply` accepts in the reference layout (float32, normals, canonical
    order) -- the layout Mitsuba's ``ellipsoids`` shape requires."""
    write_ply(dst, **read_ply(src))
