"""Compact web formats of a model: antimatter15's ``.splat`` and Niantic's ``.spz`` (read and write), from and to the
raw parameters of :class:`~mi_gaussians.model.gaussians.Gaussians` (NumPy dicts keyed by ``PARAMETER_NAMES``).

``.splat`` (antimatter15/splat ``convert.py``, read by most web viewers): no header, 32 bytes per Gaussian, rows
sorted by importance exp(s0 + s1 + s2) * opacity, largest first::

    position  3 x float32            x, y, z (the PLY's frame)
    scale     3 x float32            exp(scales)
    colour    4 x uint8              round(255 * (0.5 + SH_C0 * f_dc)), round(255 * opacity)   (clamped to 0..255)
    rotation  4 x uint8              round(128 * q / |q| + 128) of (w, x, y, z)                 (clamped to 0..255)

Degree 0 only (no higher SH bands); converter.py truncates where we round (half the error, same reader).

``.spz`` (nianticlabs/spz ``load-spz.cc``, versions 2 and 3; we write 3): a gzip stream of a 16-byte header (magic
``NGSP`` 0x5053474E, version, count, SH degree, fractional bits, flags (1: anti-aliased), 0) and sections::

    positions  9 bytes each          24-bit signed fixed point with 12 fractional bits, little-endian (x, y, z)
    alphas     1 byte                round(255 * opacity)
    colours    3 bytes               round(f_dc * 0.15 * 255 + 127.5)
    scales     3 bytes               round((log scale + 10) * 16)
    rotations  v2: 3 bytes           round(127.5 * (x, y, z) + 127.5) of the unit quaternion with w >= 0
               v3: 4 bytes           "smallest three": index of the largest component (2 bits) and the other three
                                     as sign + 9-bit magnitude of |c| * sqrt(2) (the largest is made positive)
    sh         3 per coefficient     round(128 * c) + 128, then to a multiple of 8 (band 1) or 16 (bands 2, 3)
                                     (rounded, as the reference's quantizeSH), clamped to 0..255; coefficient-major

The reference library stores its files in its internal RUB frame (x right, y up, z back) and converts from a PLY's
RDF frame (y down, z forward) when it packs one: positions (x, -y, -z), quaternions (w, x, -y, -z), and the SH
coefficients whose basis function is odd in y or z negated. We do the same, so our files open in the reference's
tools and in viewers that follow it, and convert back when reading. Version 4 (a zstd container) is refused with a
one-line error.
"""

from __future__ import annotations

import gzip
import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from ..conventions import SH_C0, logit, sh_coeff_count, sh_degree_from_coeff_count, sigmoid
from ..io_utils import atomic_write_bytes

SPLAT_ROW = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
SPZ_MAGIC = 0x5053474E
SPZ_VERSION = 3
SPZ_FRACTIONAL_BITS = 12
SPZ_COLOUR_SCALE = 0.15
SPZ_FLAG_ANTIALIASED = 0x1
#: Sign of each higher-band SH coefficient (degree 1, 2, 3 order of ``sh.py``) under y -> -y, z -> -z (RDF <-> RUB).
SPZ_SH_FLIP = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)
_FLIP_XYZ = np.array([1, -1, -1], np.float32)

FORMATS = (".ply", ".splat", ".spz")


def _u8(x) -> np.ndarray:
    return np.clip(np.round(np.asarray(x, np.float64)), 0, 255).astype(np.uint8)


def _unit_quaternions(q) -> np.ndarray:
    q = np.asarray(q, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    out = np.where(norm > 0, q / np.where(norm > 0, norm, 1), np.array([1.0, 0, 0, 0]))
    return out


def _fail(path, msg: str):
    raise ValueError(f"{path}: {msg}")


# ---------------------------------------------------------------------------------------------------- .splat
def splat_bytes(p: dict) -> bytes:
    """The ``.splat`` file of the raw parameters ``p`` (higher SH bands are dropped)."""
    scales = np.asarray(p["scales"], np.float64)
    opacity = sigmoid(np.asarray(p["opacities"], np.float64))
    order = np.argsort(-np.exp(scales.sum(axis=1)) * opacity, kind="stable")
    rows = np.zeros(len(order), SPLAT_ROW)
    rows["position"] = np.asarray(p["means"], np.float32)[order]
    rows["scale"] = np.exp(scales[order]).astype(np.float32)
    rows["rgba"][:, :3] = _u8(255.0 * (0.5 + SH_C0 * np.asarray(p["sh_dc"], np.float64)[order]))
    rows["rgba"][:, 3] = _u8(255.0 * opacity[order])
    rows["rotation"] = _u8(128.0 * _unit_quaternions(p["rotations"])[order] + 128.0)
    return rows.tobytes()


def read_splat(path) -> dict[str, np.ndarray]:
    """Raw parameters (SH degree 0) of a ``.splat`` file; opacities of 0 and 255 are read as 0.5 / 255 and
    254.5 / 255 (the logit of 0 or 1 is infinite)."""
    data = Path(path).read_bytes()
    if len(data) % SPLAT_ROW.itemsize:
        _fail(path, f"{len(data)} bytes is not a whole number of {SPLAT_ROW.itemsize}-byte .splat rows")
    if not data:
        _fail(path, "no Gaussians (empty .splat file)")
    rows = np.frombuffer(data, SPLAT_ROW)
    pos, scale = rows["position"].astype(np.float32), rows["scale"].astype(np.float64)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(scale))):
        _fail(path, "non-finite position or scale (not a .splat file?)")
    if np.any(scale <= 0):
        _fail(path, f"{int(np.sum(np.any(scale <= 0, axis=1)))} row(s) with a scale <= 0 (not a .splat file?)")
    rgba = rows["rgba"].astype(np.float64)
    alpha = np.clip(rgba[:, 3], 0.5, 254.5) / 255.0
    q = (rows["rotation"].astype(np.float64) - 128.0) / 128.0
    return {"means": pos, "scales": np.log(scale).astype(np.float32), "rotations": q.astype(np.float32),
            "opacities": logit(alpha).astype(np.float32),
            "sh_dc": ((rgba[:, :3] / 255.0 - 0.5) / SH_C0).astype(np.float32),
            "sh_rest": np.zeros((len(rows), 0, 3), np.float32)}


# ---------------------------------------------------------------------------------------------------- .spz
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


def spz_bytes(p: dict, antialiased: bool = False) -> bytes:
    """The ``.spz`` file (version 3) of the raw parameters ``p``."""
    means = np.asarray(p["means"], np.float64) * _FLIP_XYZ
    n = len(means)
    sh_rest = np.asarray(p["sh_rest"], np.float64)
    degree = sh_degree_from_coeff_count(sh_rest.shape[1] + 1)
    fixed = np.round(means * (1 << SPZ_FRACTIONAL_BITS))
    if np.any(np.abs(fixed) >= 1 << 23):
        raise ValueError(f"positions beyond +-{(1 << 23) / (1 << SPZ_FRACTIONAL_BITS):g} do not fit .spz's 24-bit "
                         "fixed point")
    pos = fixed.astype("<i4").view(np.uint8).reshape(n, 3, 4)[:, :, :3].reshape(-1)
    alphas = _u8(255.0 * sigmoid(np.asarray(p["opacities"], np.float64)))
    colours = _u8(np.asarray(p["sh_dc"], np.float64) * (SPZ_COLOUR_SCALE * 255.0) + 127.5)
    scales = _u8((np.asarray(p["scales"], np.float64) + 10.0) * 16.0)
    q = _unit_quaternions(p["rotations"]) * np.array([1.0, 1.0, -1.0, -1.0])
    rotations = pack_smallest_three(q)
    k = sh_rest.shape[1]
    sh = sh_rest * SPZ_SH_FLIP[:k, None]
    bucket = np.where(np.arange(k) < 3, 8, 16)[None, :, None]
    sh_bytes = np.zeros(sh.shape, np.uint8)
    for b in (8, 16):
        sel = np.broadcast_to(bucket == b, sh.shape)
        sh_bytes[sel] = _quantize_sh(sh[sel], b)
    header = struct.pack("<IIIBBBB", SPZ_MAGIC, SPZ_VERSION, n, degree, SPZ_FRACTIONAL_BITS,
                         SPZ_FLAG_ANTIALIASED if antialiased else 0, 0)
    body = b"".join(a.tobytes() for a in (pos, alphas, colours, scales, rotations, sh_bytes))
    return gzip.compress(header + body, compresslevel=6, mtime=0)


def read_spz(path) -> tuple[dict[str, np.ndarray], bool]:
    """(raw parameters, anti-aliased flag) of a ``.spz`` file, versions 2 and 3."""
    raw = Path(path).read_bytes()
    if raw[:4] == struct.pack("<I", SPZ_MAGIC):
        version = struct.unpack("<I", raw[4:8])[0] if len(raw) >= 8 else 0
        _fail(path, f".spz version {version} (the zstd container) is not supported; versions 2 and 3 are")
    try:
        data = gzip.decompress(raw)
    except (OSError, EOFError, zlib.error) as e:          # (gzip.BadGzipFile is an OSError)
        _fail(path, f"not a gzip-compressed .spz file, or a damaged one ({e})")
    if len(data) < 16:
        _fail(path, f"truncated .spz header ({len(data)} of 16 bytes)")
    magic, version, n, degree, frac, flags, _ = struct.unpack("<IIIBBBB", data[:16])
    if magic != SPZ_MAGIC:
        _fail(path, f"not a .spz file (magic 0x{magic:08X}, expected 0x{SPZ_MAGIC:08X})")
    if version not in (2, 3):
        _fail(path, f".spz version {version} is not supported (2 and 3 are)")
    if degree > 3:
        _fail(path, f"SH degree {degree} (at most 3)")
    if n == 0:
        _fail(path, "no Gaussians")
    if frac > 23:
        _fail(path, f"{frac} fractional bits (at most 23)")
    k = sh_coeff_count(degree) - 1
    rot_bytes = 4 if version == 3 else 3
    need = 16 + n * (9 + 1 + 3 + 3 + rot_bytes + 3 * k)
    if len(data) != need:
        _fail(path, f"{len(data)} bytes after decompression, {need} expected for {n:,} Gaussians of SH degree "
                    f"{degree}")
    off = 16

    def take(size):
        nonlocal off
        out = np.frombuffer(data, np.uint8, size, off)
        off += size
        return out

    pos = take(9 * n).reshape(n, 3, 3).astype(np.int32)
    fixed = pos[:, :, 0] | (pos[:, :, 1] << 8) | (pos[:, :, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.astype(np.float64) / (1 << frac) * _FLIP_XYZ
    alpha = np.clip(take(n).astype(np.float64), 0.5, 254.5) / 255.0
    colours = (take(3 * n).reshape(n, 3).astype(np.float64) - 127.5) / (SPZ_COLOUR_SCALE * 255.0)
    scales = take(3 * n).reshape(n, 3).astype(np.float64) / 16.0 - 10.0
    if version == 3:
        q = unpack_smallest_three(take(4 * n).reshape(n, 4))
    else:
        xyz = take(3 * n).reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        q = np.concatenate([np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1)))[:, None], xyz], axis=1)
    q = q * np.array([1.0, 1.0, -1.0, -1.0])
    sh = (take(3 * k * n).reshape(n, k, 3).astype(np.float64) - 128.0) / 128.0 * SPZ_SH_FLIP[:k, None]
    params = {"means": means.astype(np.float32), "scales": scales.astype(np.float32),
              "rotations": q.astype(np.float32), "opacities": logit(alpha).astype(np.float32),
              "sh_dc": colours.astype(np.float32), "sh_rest": sh.astype(np.float32)}
    return params, bool(flags & SPZ_FLAG_ANTIALIASED)


# ---------------------------------------------------------------------------------------------------- any
def drop_sh_bands(p: dict, degree: int) -> dict:
    """``p`` with its SH bands above ``degree`` removed (``degree`` at most the model's)."""
    have = sh_degree_from_coeff_count(np.asarray(p["sh_rest"]).shape[1] + 1)
    if not 0 <= degree <= have:
        raise ValueError(f"--sh-degree {degree}: the model has SH degree {have}")
    return {**p, "sh_rest": np.asarray(p["sh_rest"])[:, : sh_coeff_count(degree) - 1]}


def read_model(path) -> tuple[dict[str, np.ndarray], bool | None]:
    """(raw parameters, anti-aliased flag or None when the format does not say) of a ``.ply``, ``.splat`` or
    ``.spz`` file, by its suffix."""
    from .ply import read_ply

    suffix = Path(path).suffix.lower()
    if suffix == ".splat":
        return read_splat(path), None
    if suffix == ".spz":
        return read_spz(path)
    if suffix == ".ply":
        return read_ply(path, renderable=True), None
    raise ValueError(f"{path}: unknown model format {suffix!r} (expected one of {', '.join(FORMATS)})")


def write_model(path, p: dict, antialiased: bool = False) -> None:
    """Write the raw parameters ``p`` as ``.ply``, ``.splat`` or ``.spz`` (by the suffix), atomically."""
    from .ply import write_ply

    suffix = Path(path).suffix.lower()
    if suffix == ".ply":
        write_ply(path, **p)
    elif suffix == ".splat":
        atomic_write_bytes(path, splat_bytes(p))
    elif suffix == ".spz":
        atomic_write_bytes(path, spz_bytes(p, antialiased=antialiased))
    else:
        raise ValueError(f"{os.fspath(path)}: unknown model format {suffix!r} (expected one of {', '.join(FORMATS)})")
