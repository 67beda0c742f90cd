"""Niantic's ``.spz`` (nianticlabs/spz ``load-spz.cc`` and its README): versions 2, 3 and 4 read, 3 and 4 written
(4 by default, as the reference library and PlayCanvas splat-transform write), from and to the raw parameters of
:class:`~mi_gaussians.model.gaussians.Gaussians` (NumPy dicts keyed by ``PARAMETER_NAMES``).

Versions 2 and 3 are one gzip stream of a 16-byte header (magic ``NGSP`` 0x5053474E, version, count, SH degree,
fractional bits, flags, 0), the sections below back to back and, when flags has 0x2, extension records. Version 4 is a
32-byte plain header (magic, version, count, SH degree, fractional bits, flags, number of streams, offset of the table
of contents, 12 zero bytes), extension records up to that offset (flags 0x2), the table of contents (per stream its
compressed and uncompressed size, u64 each) and one zstd frame per non-empty section, in this order::

    positions  9 bytes each          24-bit signed fixed point with 12 fractional bits, little-endian (x, y, z)
    alphas     1 byte                round(255 * opacity)
    colours    3 bytes               round(f_dc * 0.15 * 255 + 127.5)
    scales     3 bytes               round((log scale + 10) * 16)
    rotations  v2: 3 bytes           round(127.5 * (x, y, z) + 127.5) of the unit quaternion with w >= 0
               v3, v4: 4 bytes       "smallest three": index of the largest component (2 bits) and the other three
                                     as sign + 9-bit magnitude of |c| * sqrt(2) (the largest is made positive)
    sh         3 per coefficient     round(128 * c) + 128, then to a multiple of 8 (band 1) or 16 (bands 2, 3)
                                     (rounded, as the reference's quantizeSH), clamped to 0..255; coefficient-major

Flags 0x1: trained anti-aliased. Extension records are (u32 type, u32 length, payload); the only one that changes the
data is Adobe's coordinate system (0xADBE0003), honoured for the eight axis-flip frames and refused for the others.

The frame: the spz README names RUB (x right, y up, z back) as the format's storage frame, but its library converts
only between frames its caller names, and by default names none (``CoordinateSystem::UNSPECIFIED``): its own
``ply_to_spz`` stores a PLY's coordinates as they are, PlayCanvas splat-transform writes through that library with
UNSPECIFIED and reads an ``.spz`` as PLY-frame data, and Spark and three.js' SPZLoader show an ``.spz`` as they show the
PLY it came from. We do the same: an ``.spz`` holds the model's own coordinates (the PLY's), so our files and theirs
open the same way everywhere. A file that names its frame with Adobe's coordinate-system extension is turned from
that frame to the PLY's (RDF) with :func:`.frames.flip_axes`. (mi-gs before the SPZ v4 support wrote RUB: such
files read back turned by 180 degrees about x.)
"""

from __future__ import annotations

import gzip
import math
import struct
import zlib
from pathlib import Path

import numpy as np

from ..conventions import logit, sh_coeff_count, sh_degree_from_coeff_count, sigmoid
from .frames import flip_axes

SPZ_MAGIC = 0x5053474E
SPZ_VERSIONS_WRITTEN = (3, 4)
SPZ_DEFAULT_VERSION = 4
SPZ_FRACTIONAL_BITS = 12
SPZ_COLOUR_SCALE = 0.15
SPZ_FLAG_ANTIALIASED = 0x1
SPZ_FLAG_EXTENSIONS = 0x2
SPZ_ZSTD_LEVEL = 12                        # the reference's compressZstd default
SPZ_V4_HEADER = struct.Struct("<IIIBBBBI12x")
SPZ_LEGACY_HEADER = struct.Struct("<IIIBBBB")
#: Adobe's SPZ_ADOBE_coordinate_system values 1..8 (the axis-flip family): the axes' directions.
_COORDINATE_SYSTEMS = {1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF"}
_EXT_COORDINATE_SYSTEM = 0xADBE0003


def _u8(x) -> np.ndarray:
    return np.clip(np.round(np.asarray(x, np.float64)), 0, 255).astype(np.uint8)


def unit_quaternions(q) -> np.ndarray:
    """(N, 4) quaternions normalized; zero ones become the identity."""
    q = np.asarray(q, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(norm > 0, q / np.where(norm > 0, norm, 1), np.array([1.0, 0, 0, 0]))


def _fail(path, msg: str):
    raise ValueError(f"{path}: {msg}")


def pack_smallest_three(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit (w, x, y, z) quaternions -> (N, 4) bytes of the v3 encoding (components in (x, y, z, w) order)."""
    xyzw = q[:, [1, 2, 3, 0]]
    largest = np.argmax(np.abs(xyzw), axis=1)
    sign = np.where(xyzw[np.arange(len(q)), largest] < 0, -1.0, 1.0)
    xyzw = xyzw * sign[:, None]
    packed = largest.astype(np.uint32)
    mask = (1 << 9) - 1
    for i in range(4):
        keep = largest != i
        c = xyzw[:, i]
        mag = np.clip(np.round(mask * np.abs(c) * math.sqrt(2.0)), 0, mask).astype(np.uint32)
        bits = ((c < 0).astype(np.uint32) << 9) | mag
        packed = np.where(keep, (packed << 10) | bits, packed)
    return packed.astype("<u4").view(np.uint8).reshape(-1, 4)


def unpack_smallest_three(b: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_smallest_three`: (N, 4) bytes -> (N, 4) (w, x, y, z)."""
    packed = b.copy().view("<u4").reshape(-1).astype(np.uint32)
    largest = packed >> 30
    xyzw = np.zeros((len(packed), 4), np.float64)
    mask = (1 << 9) - 1
    rest = packed.copy()
    for i in (3, 2, 1, 0):
        keep = largest != i
        mag = (rest & mask).astype(np.float64) / mask / math.sqrt(2.0)
        neg = ((rest >> 9) & 1).astype(bool)
        xyzw[:, i] = np.where(keep, np.where(neg, -mag, mag), 0.0)
        rest = np.where(keep, rest >> 10, rest)
    idx = np.arange(len(packed))
    xyzw[idx, largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyzw * xyzw, axis=1)))
    return xyzw[:, [3, 0, 1, 2]]


def _quantize_sh(c: np.ndarray, bucket: int) -> np.ndarray:
    q = np.round(np.asarray(c, np.float64) * 128.0) + 128.0
    q = np.floor((q + bucket / 2) / bucket) * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------------- writing
def _sections(p: dict) -> tuple[int, int, list[bytes]]:
    """(count, SH degree, the six sections' bytes) of the raw parameters ``p`` (their own frame: see above)."""
    sh_rest = np.asarray(p["sh_rest"], np.float64)
    degree = sh_degree_from_coeff_count(sh_rest.shape[1] + 1)
    n = len(p["means"])
    fixed = np.round(np.asarray(p["means"], np.float64) * (1 << SPZ_FRACTIONAL_BITS))
    if np.any(np.abs(fixed) >= 1 << 23):
        raise ValueError(f"positions beyond +-{(1 << 23) / (1 << SPZ_FRACTIONAL_BITS):g} do not fit .spz's 24-bit "
                         "fixed point")
    pos = fixed.astype("<i4").view(np.uint8).reshape(n, 3, 4)[:, :, :3].reshape(-1)
    alphas = _u8(255.0 * sigmoid(np.asarray(p["opacities"], np.float64)))
    colours = _u8(np.asarray(p["sh_dc"], np.float64) * (SPZ_COLOUR_SCALE * 255.0) + 127.5)
    scales = _u8((np.asarray(p["scales"], np.float64) + 10.0) * 16.0)
    rotations = pack_smallest_three(unit_quaternions(p["rotations"]))
    sh = sh_rest
    k = sh_rest.shape[1]
    bucket = np.where(np.arange(k) < 3, 8, 16)[None, :, None]
    sh_bytes = np.zeros(sh.shape, np.uint8)
    for b in (8, 16):
        sel = np.broadcast_to(bucket == b, sh.shape)
        sh_bytes[sel] = _quantize_sh(sh[sel], b)
    return n, degree, [a.tobytes() for a in (pos, alphas, colours, scales, rotations, sh_bytes)]


def spz_bytes(p: dict, antialiased: bool = False, version: int = SPZ_DEFAULT_VERSION) -> bytes:
    """The ``.spz`` file (``version`` 3: gzip, or 4: zstd streams) of the raw parameters ``p``."""
    if version not in SPZ_VERSIONS_WRITTEN:
        raise ValueError(f".spz version {version} cannot be written (only 3 and 4)")
    n, degree, sections = _sections(p)
    flags = SPZ_FLAG_ANTIALIASED if antialiased else 0
    if version == 3:
        header = SPZ_LEGACY_HEADER.pack(SPZ_MAGIC, 3, n, degree, SPZ_FRACTIONAL_BITS, flags, 0)
        return gzip.compress(header + b"".join(sections), compresslevel=6, mtime=0)
    import zstandard

    compressor = zstandard.ZstdCompressor(level=SPZ_ZSTD_LEVEL)
    streams = [(compressor.compress(s), len(s)) for s in sections if s]
    header = SPZ_V4_HEADER.pack(SPZ_MAGIC, 4, n, degree, SPZ_FRACTIONAL_BITS, flags, len(streams), SPZ_V4_HEADER.size)
    toc = b"".join(struct.pack("<QQ", len(c), u) for c, u in streams)
    return header + toc + b"".join(c for c, _ in streams)


# ---------------------------------------------------------------------------------------------------- reading
def _frame_signs(path, records: bytes) -> tuple[float, float, float]:
    """The axis flip from the file's stored frame to the model's RDF, from its extension ``records``: none, unless
    Adobe's coordinate-system extension names a frame."""
    signs = (1.0, 1.0, 1.0)
    off = 0
    while off + 8 <= len(records):
        kind, size = struct.unpack_from("<II", records, off)
        payload = records[off + 8: off + 8 + size]
        if len(payload) != size:
            _fail(path, f"damaged extension record at byte {off} of the extensions ({size} bytes announced)")
        if kind == _EXT_COORDINATE_SYSTEM and size >= 4:
            value = struct.unpack_from("<I", payload)[0]
            if value not in (0, *_COORDINATE_SYSTEMS):
                _fail(path, f"stores its Gaussians in coordinate system {value} (SPZ_ADOBE_coordinate_system), a "
                            "rotated frame that is not read (only the axis-flip frames 1-8)")
            name = _COORDINATE_SYSTEMS.get(value, "RUB")           # (UNSPECIFIED: the reference reads RUB)
            signs = tuple(1.0 if a == b else -1.0 for a, b in zip(name, "RDF"))
        off += 8 + size
    return signs


def _decode(path, version: int, n: int, degree: int, frac: int, sections: list[np.ndarray]) -> dict:
    pos, alpha_b, colour_b, scale_b, rot_b, sh_b = sections
    k = sh_coeff_count(degree) - 1
    pos = pos.reshape(n, 3, 3).astype(np.int32)
    fixed = pos[:, :, 0] | (pos[:, :, 1] << 8) | (pos[:, :, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    alpha = np.clip(alpha_b.astype(np.float64), 0.5, 254.5) / 255.0
    if version >= 3:
        q = unpack_smallest_three(rot_b.reshape(n, 4))
    else:
        xyz = rot_b.reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        q = np.concatenate([np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1)))[:, None], xyz], axis=1)
    return {"means": (fixed.astype(np.float64) / (1 << frac)).astype(np.float32),
            "scales": (scale_b.reshape(n, 3).astype(np.float64) / 16.0 - 10.0).astype(np.float32),
            "rotations": q.astype(np.float32), "opacities": logit(alpha).astype(np.float32),
            "sh_dc": ((colour_b.reshape(n, 3) - 127.5) / (SPZ_COLOUR_SCALE * 255.0)).astype(np.float32),
            "sh_rest": ((sh_b.reshape(n, k, 3).astype(np.float64) - 128.0) / 128.0).astype(np.float32)}


def _section_sizes(n: int, degree: int, version: int) -> list[int]:
    k = sh_coeff_count(degree) - 1
    return [9 * n, n, 3 * n, 3 * n, (4 if version >= 3 else 3) * n, 3 * k * n]


def _check_header(path, version: int, n: int, degree: int, frac: int) -> None:
    if degree > 3:
        _fail(path, f"SH degree {degree} (at most 3)")
    if n == 0:
        _fail(path, "no Gaussians")
    if frac > 23:
        _fail(path, f"{frac} fractional bits (at most 23)")


def _read_legacy(path, raw: bytes):
    try:
        data = gzip.decompress(raw)
    except (OSError, EOFError, zlib.error) as e:          # (gzip.BadGzipFile is an OSError)
        _fail(path, f"not a gzip-compressed .spz file, or a damaged one ({e})")
    if len(data) < 16:
        _fail(path, f"truncated .spz header ({len(data)} of 16 bytes)")
    magic, version, n, degree, frac, flags, _ = SPZ_LEGACY_HEADER.unpack(data[:16])
    if magic != SPZ_MAGIC:
        _fail(path, f"not a .spz file (magic 0x{magic:08X}, expected 0x{SPZ_MAGIC:08X})")
    if version not in (2, 3):
        _fail(path, f".spz version {version} in a gzip stream is not supported (2 and 3 are; 4 is not gzipped)")
    _check_header(path, version, n, degree, frac)
    sizes = _section_sizes(n, degree, version)
    need = 16 + sum(sizes)
    if len(data) < need or (len(data) != need and not flags & SPZ_FLAG_EXTENSIONS):
        _fail(path, f"{len(data)} bytes after decompression, {need} expected for {n:,} Gaussians of SH degree "
                    f"{degree}")
    offsets = np.cumsum([16] + sizes)
    sections = [np.frombuffer(data, np.uint8, s, int(o)) for s, o in zip(sizes, offsets)]
    return version, n, degree, frac, flags, sections, data[need:]


def _read_v4(path, raw: bytes):
    if len(raw) < SPZ_V4_HEADER.size:
        _fail(path, f"truncated .spz header ({len(raw)} of {SPZ_V4_HEADER.size} bytes)")
    magic, version, n, degree, frac, flags, streams, toc = SPZ_V4_HEADER.unpack(raw[:SPZ_V4_HEADER.size])
    if version != 4:
        _fail(path, f".spz version {version} is not supported (2, 3 and 4 are)")
    _check_header(path, version, n, degree, frac)
    sizes = [s for s in _section_sizes(n, degree, version) if s]
    if streams != len(sizes):
        _fail(path, f"{streams} streams, {len(sizes)} expected for SH degree {degree}")
    end = toc + 16 * streams
    if toc < SPZ_V4_HEADER.size or end > len(raw):
        _fail(path, f"table of contents at byte {toc} does not fit the file's {len(raw)} bytes (truncated?)")
    entries = [struct.unpack_from("<QQ", raw, toc + 16 * i) for i in range(streams)]
    if end + sum(c for c, _ in entries) != len(raw):
        _fail(path, f"{len(raw)} bytes, {end + sum(c for c, _ in entries)} announced by its table of contents "
                    "(truncated or damaged)")
    import zstandard

    sections, off = [], end
    for i, ((comp, size), want) in enumerate(zip(entries, sizes)):
        if size != want:
            _fail(path, f"stream {i} holds {size} bytes, {want} expected for {n:,} Gaussians of SH degree {degree}")
        try:
            out = zstandard.ZstdDecompressor().decompress(raw[off:off + comp], max_output_size=size)
        except zstandard.ZstdError as e:
            _fail(path, f"damaged zstd stream {i} ({e})")
        if len(out) != size:
            _fail(path, f"stream {i} decompresses to {len(out)} bytes, {size} announced")
        sections.append(np.frombuffer(out, np.uint8))
        off += comp
    sections += [np.zeros(0, np.uint8)] * (6 - len(sections))        # (degree 0: no SH stream)
    return version, n, degree, frac, flags, sections, raw[SPZ_V4_HEADER.size:toc]


def read_spz_bytes(path, raw: bytes) -> tuple[dict[str, np.ndarray], dict]:
    """(raw parameters, {"version", "antialiased"}) of the ``.spz`` file ``raw`` (``path`` names it in errors)."""
    if raw[:4] == struct.pack("<I", SPZ_MAGIC):
        version, n, degree, frac, flags, sections, ext = _read_v4(path, raw)
    else:
        version, n, degree, frac, flags, sections, ext = _read_legacy(path, raw)
    signs = _frame_signs(path, ext if flags & SPZ_FLAG_EXTENSIONS else b"")
    params = flip_axes(_decode(path, version, n, degree, frac, sections), signs)
    return params, {"version": version, "antialiased": bool(flags & SPZ_FLAG_ANTIALIASED)}


def read_spz(path) -> tuple[dict[str, np.ndarray], bool]:
    """(raw parameters, anti-aliased flag) of a ``.spz`` file, versions 2, 3 and 4."""
    params, meta = read_spz_bytes(path, Path(path).read_bytes())
    return params, meta["antialiased"]
