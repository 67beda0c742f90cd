"""The model file formats and the one place that picks a reader or a writer by the file's suffix: the 3DGS PLY
(:mod:`.ply`), antimatter15's ``.splat`` (here), Niantic's ``.spz`` (:mod:`.spz`) and glTF 2.0 with
``KHR_gaussian_splatting`` (``.glb``, ``.gltf``: :mod:`.gltf`), from and to the raw parameters of
:class:`~mi_gaussians.model.gaussians.Gaussians` (NumPy dicts keyed by ``PARAMETER_NAMES``).

``.splat`` (antimatter15/splat ``convert.py``, read by most web viewers): no header, 32 bytes per Gaussian, rows
sorted by importance exp(s0 + s1 + s2) * opacity, largest first::

    position  3 x float32            x, y, z (the PLY's frame)
    scale     3 x float32            exp(scales)
    colour    4 x uint8              round(255 * (0.5 + SH_C0 * f_dc)), round(255 * opacity)   (clamped to 0..255)
    rotation  4 x uint8              round(128 * q / |q| + 128) of (w, x, y, z)                 (clamped to 0..255)

Degree 0 only (no higher SH bands); converter.py truncates where we round (half the error, same reader).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..conventions import SH_C0, logit, sh_coeff_count, sh_degree_from_coeff_count, sigmoid
from ..io_utils import atomic_write_bytes, atomic_write_text
from .spz import SPZ_DEFAULT_VERSION, read_spz_bytes, spz_bytes, unit_quaternions

SPLAT_ROW = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
FORMATS = (".ply", ".splat", ".spz", ".glb", ".gltf")


def _u8(x) -> np.ndarray:
    return np.clip(np.round(np.asarray(x, np.float64)), 0, 255).astype(np.uint8)


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
    rows["rotation"] = _u8(128.0 * unit_quaternions(p["rotations"])[order] + 128.0)
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


# ---------------------------------------------------------------------------------------------------- any
def drop_sh_bands(p: dict, degree: int) -> dict:
    """``p`` with its SH bands above ``degree`` removed (``degree`` at most the model's)."""
    have = sh_degree_from_coeff_count(np.asarray(p["sh_rest"]).shape[1] + 1)
    if not 0 <= degree <= have:
        raise ValueError(f"--sh-degree {degree}: the model has SH degree {have}")
    return {**p, "sh_rest": np.asarray(p["sh_rest"])[:, : sh_coeff_count(degree) - 1]}


def read_model_info(path) -> tuple[dict[str, np.ndarray], dict]:
    """(raw parameters, what the file says beside them) of a model file, by its suffix: ``format`` always;
    ``antialiased`` (``.spz``'s flag), ``version`` (``.spz``), ``color_space`` and ``generator`` (glTF)."""
    from .gltf import read_gltf
    from .ply import read_ply

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".splat":
        return read_splat(path), {"format": "splat"}
    if suffix == ".spz":
        params, meta = read_spz_bytes(path, path.read_bytes())
        return params, {"format": "spz", **meta}
    if suffix in (".glb", ".gltf"):
        params, meta = read_gltf(path)
        return params, {"format": suffix[1:], **meta}
    if suffix == ".ply":
        return read_ply(path, renderable=True), {"format": "ply"}
    raise ValueError(f"{path}: unknown model format {suffix!r} (expected one of {', '.join(FORMATS)})")


def read_model(path) -> tuple[dict[str, np.ndarray], bool | None]:
    """(raw parameters, anti-aliased flag or None when the format does not say) of a model file, by its suffix."""
    params, meta = read_model_info(path)
    return params, meta.get("antialiased")


def write_model(path, p: dict, antialiased: bool = False, spz_version: int = SPZ_DEFAULT_VERSION,
                color_space: str = "srgb") -> None:
    """Write the raw parameters ``p`` as ``.ply``, ``.splat``, ``.spz`` (``spz_version`` 3 or 4, the anti-aliased
    flag) or ``.glb`` / ``.gltf`` (``color_space``: what the model's colours are), by the suffix, atomically."""
    from .gltf import glb_bytes, gltf_text
    from .ply import write_ply

    suffix = Path(path).suffix.lower()
    if suffix == ".ply":
        write_ply(path, **p)
    elif suffix == ".splat":
        atomic_write_bytes(path, splat_bytes(p))
    elif suffix == ".spz":
        atomic_write_bytes(path, spz_bytes(p, antialiased=antialiased, version=spz_version))
    elif suffix == ".glb":
        atomic_write_bytes(path, glb_bytes(p, color_space))
    elif suffix == ".gltf":
        atomic_write_text(path, gltf_text(p, color_space))
    else:
        raise ValueError(f"{os.fspath(path)}: unknown model format {suffix!r} (expected one of {', '.join(FORMATS)})")
