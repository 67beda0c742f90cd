"""Frames, layouts and the small converters between them.

The converters work on NumPy arrays and hold no state; only :func:`ellipsoids_shape_dict` makes Dr.Jit tensors (for
``mi.load_dict``), so it needs a Mitsuba variant to be set.

Frames
------
* World space: whatever the scene / dataset uses; Gaussians live there (``means`` are world positions).
* Camera space (ours, COLMAP, OpenCV, Mitsuba's pinhole projection): x right, y down, z forward. A camera-space point
  ``(x, y, z)`` projects to pixel ``(fx x / z + cx, fy y / z + cy)`` and pixel ``(i, j)`` is sampled at its centre
  ``(i + 0.5, j + 0.5)``. Blender / NeRF-synthetic cameras (OpenGL: y up, z back) are converted by flipping the camera's
  y and z axes (done in :mod:`mi_gaussians.data`).
* View direction for the SH colour: ``normalize(mean - camera_centre)`` (from the camera towards the Gaussian), exactly as
  the reference ``computeColorFromSH``; see :mod:`mi_gaussians.model.sh`.

Layouts of the raw parameters (``N`` Gaussians, ``K = (degree + 1)^2`` SH coefficients per colour channel)
--------------------------------------------------------------------------------------------------------------
* Quaternions: ours and the 3DGS PLY store ``(w, x, y, z)`` (``rot_0`` is the real part), unnormalized.
  Dr.Jit's ``dr.Quaternion4f`` and Mitsuba's ``ellipsoids`` shape use ``(x, y, z, w)``.
* SH, ours (``Gaussians.sh_rest``): coefficient-major ``(N, K - 1, 3)`` -- band index, then RGB.
* SH, 3DGS PLY ``f_rest_*``: channel-major ``(N, 3 * (K - 1))`` -- all R coefficients of bands 1.., then all G, then B.
  ``f_dc_0..2`` are the degree-0 coefficients of R, G, B.
* SH, Mitsuba ``ellipsoids`` ``sh_coeffs``: ``(N, 3 * K)`` coefficient-major and RGB-interleaved, DC included:
  ``[dc_R, dc_G, dc_B, c1_R, c1_G, c1_B, ...]`` == ``concatenate([sh_dc[:, None], sh_rest], 1).reshape(N, 3 * K)``.
* Activations: ``sigma = exp(scale)``, ``alpha = sigmoid(opacity)``, colour = ``max(SH(dir) + 0.5, 0)``,
  DC <-> RGB: ``dc = (rgb - 0.5) / SH_C0``.

Mitsuba 3.9.1 ``ellipsoids`` shape (``src/shapes/ellipsoids.h``, verified against the installed binary in
``tests/test_conventions.py`` and ``tests/test_ply.py``)
-----------------------------------------------------------------------------------------------------------------
Loading a 3DGS PLY (``{"type": "ellipsoids", "filename": path}``):

* The vertex properties must start with ``x y z nx ny nz`` and end with ``scale_0..2 rot_0..3`` (otherwise
  "Invalid structure in PLY file!"); the file is taken as 3DGS when property 6 is ``f_dc_0`` and the 8th from the end is
  ``opacity``. Every property is read as float32 (no type conversion), so the file must be all-float32 -- the exact
  layout :func:`mi_gaussians.model.ply.write_ply` writes. PLYs without normals (some SuperSplat/gsplat exports) are
  rejected: rewrite them with :func:`mi_gaussians.model.ply.convert_ply`.
* It stores ACTIVATED values, in float32:
  - ``data``: flat ``N * 10`` floats, per ellipsoid ``[cx, cy, cz, sx, sy, sz, qx, qy, qz, qw]`` with
    ``centre = to_world(x, y, z)``, ``s = max(exp(scale), 1e-6) * scale_factor * mean(diag(S(to_world)))`` (so the
    standard deviations sigma, floored at 1e-6; ``scale_factor`` defaults to 1) and the quaternion
    ``normalize(Q(to_world) * (rot_1, rot_2, rot_3, rot_0))`` -- reordered to (x, y, z, w) and NORMALIZED (a zero
    quaternion gives NaN); no sign canonicalization.
  - ``opacities``: ``N`` floats, ``clip(1 / (1 + exp(-opacity)), 1e-8, 1 - 1e-8)`` (the upper bound rounds to 1.0 in
    float32).
  - ``sh_coeffs``: ``N * 3K`` floats in the interleaved coefficient-major layout above (DC first).
* ``mi.traverse(shape)`` keys (prefixed ``<id>.`` inside a scene): ``data`` (differentiable, flat Float),
  ``sh_coeffs`` (differentiable), ``opacities`` (differentiable), ``extent`` (read-only float, default 3.0: the support
  of each ellipsoid in sigmas, NOT a scale on sigma), ``extent_adaptive_clamping`` (read-only bool, default False).
* Alternatively ``{"type": "ellipsoids", "data": TensorXf (N, 10), "opacities": TensorXf (N, 1),
  "sh_coeffs": TensorXf (N, 3K)}`` stores the given values unchanged (no activation, no normalization; every extra
  attribute must be a 2-D tensor with N rows). :func:`ellipsoids_shape_dict` builds that dictionary.
"""

from __future__ import annotations

import math

import numpy as np

#: Degree-0 real SH constant, 1 / (2 sqrt(pi)).
SH_C0 = 0.28209479177387814

#: Floats per ellipsoid in the ``data`` buffer of Mitsuba's ``ellipsoids`` shape: centre (3), sigma (3), quat xyzw (4).
ELLIPSOID_STRUCT_SIZE = 10
#: The ``ellipsoids`` PLY loader floors ``exp(scale)`` at this value.
ELLIPSOIDS_SIGMA_FLOOR = 1e-6
#: The ``ellipsoids`` PLY loader clips ``sigmoid(opacity)`` to ``[lo, hi]`` (computed in float32: hi == 1.0).
ELLIPSOIDS_OPACITY_CLIP = (1e-8, 1.0 - 1e-8)


def _float_array(a) -> np.ndarray:
    """``a`` as an array of its own float dtype (non-float input becomes float64)."""
    a = np.asarray(a)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    return a


# ---------------------------------------------------------------------------------------------------- quaternions
def quat_wxyz_to_xyzw(q) -> np.ndarray:
    """``(..., 4)`` quaternions ``(w, x, y, z)`` -> ``(x, y, z, w)`` (a copy, values untouched)."""
    q = np.asarray(q)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternions must have a last axis of size 4, got shape {q.shape}")
    return np.ascontiguousarray(q[..., [1, 2, 3, 0]])


def quat_xyzw_to_wxyz(q) -> np.ndarray:
    """``(..., 4)`` quaternions ``(x, y, z, w)`` -> ``(w, x, y, z)`` (a copy, values untouched)."""
    q = np.asarray(q)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternions must have a last axis of size 4, got shape {q.shape}")
    return np.ascontiguousarray(q[..., [3, 0, 1, 2]])


def normalize_quat(q) -> np.ndarray:
    """``(..., 4)`` quaternions divided by their norm, in the input's float dtype (zero quaternions give NaN)."""
    q = _float_array(q)
    with np.errstate(invalid="ignore", divide="ignore"):
        return q / np.linalg.norm(q, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------------- SH layouts
def sh_coeff_count(degree: int) -> int:
    """SH coefficients per colour channel for a degree: ``K = (degree + 1)^2`` (the inverse of
    :func:`sh_degree_from_coeff_count`)."""
    return (int(degree) + 1) ** 2


def sh_degree_from_coeff_count(k: int) -> int:
    """SH degree ``d`` in 0..3 from the number of coefficients per channel ``K = (d + 1)^2``; ValueError otherwise."""
    d = int(round(math.sqrt(max(k, 0)))) - 1
    if d < 0 or d > 3 or sh_coeff_count(d) != k:
        raise ValueError(f"{k} SH coefficients per channel is not (d + 1)^2 for a degree d in 0..3")
    return d


def sh_channel_major_to_coeff_major(f_rest) -> np.ndarray:
    """3DGS PLY ``f_rest`` ``(N, 3 (K - 1))`` (R coefficients, then G, then B) -> ours ``(N, K - 1, 3)``.

    Pure reordering: the values are copied bit for bit."""
    f_rest = np.asarray(f_rest)
    if f_rest.ndim != 2 or f_rest.shape[1] % 3:
        raise ValueError(f"f_rest must have shape (N, 3 * (K - 1)), got {f_rest.shape}")
    n, m = f_rest.shape
    return np.ascontiguousarray(f_rest.reshape(n, 3, m // 3).transpose(0, 2, 1))


def sh_coeff_major_to_channel_major(sh_rest) -> np.ndarray:
    """Ours ``(N, K - 1, 3)`` -> 3DGS PLY ``f_rest`` ``(N, 3 (K - 1))`` channel-major. Bit-exact copy."""
    sh_rest = np.asarray(sh_rest)
    if sh_rest.ndim != 3 or sh_rest.shape[2] != 3:
        raise ValueError(f"sh_rest must have shape (N, K - 1, 3), got {sh_rest.shape}")
    n = sh_rest.shape[0]
    return np.ascontiguousarray(sh_rest.transpose(0, 2, 1).reshape(n, 3 * sh_rest.shape[1]))


# ---------------------------------------------------------------------------------------------------- colour / opacity
def rgb_to_sh_dc(rgb) -> np.ndarray:
    """RGB in [0, 1] ``(..., 3)`` -> degree-0 SH coefficients ``(rgb - 0.5) / SH_C0`` (input's float dtype)."""
    rgb = _float_array(rgb)
    return ((rgb - 0.5) / SH_C0).astype(rgb.dtype, copy=False)


def sh_dc_to_rgb(dc) -> np.ndarray:
    """Degree-0 SH coefficients ``(..., 3)`` -> RGB ``dc * SH_C0 + 0.5`` (unclamped; input's float dtype)."""
    dc = _float_array(dc)
    return (dc * SH_C0 + 0.5).astype(dc.dtype, copy=False)


def sigmoid(x) -> np.ndarray:
    """Numerically stable logistic function, computed in float64, returned in the input's float dtype."""
    x = _float_array(x)
    x64 = x.astype(np.float64)
    out = np.empty_like(x64)
    pos = x64 >= 0
    with np.errstate(under="ignore"):
        out[pos] = 1.0 / (1.0 + np.exp(-x64[pos]))
        e = np.exp(x64[~pos])
        out[~pos] = e / (1.0 + e)
    return out.astype(x.dtype, copy=False)


def logit(p) -> np.ndarray:
    """Inverse of :func:`sigmoid`, ``log(p / (1 - p))`` in float64, returned in the input's float dtype.

    Raises ValueError unless every value is strictly inside (0, 1)."""
    p = _float_array(p)
    p64 = p.astype(np.float64)
    bad = ~((p64 > 0.0) & (p64 < 1.0))
    if np.any(bad):
        raise ValueError(f"logit needs values strictly inside (0, 1); {int(bad.sum())} value(s) are not")
    return (np.log(p64) - np.log1p(-p64)).astype(p.dtype, copy=False)


# ---------------------------------------------------------------------------------------------------- Mitsuba ellipsoids
def to_ellipsoids_layout(means, scales, rotations, opacities, sh_dc, sh_rest=None) -> dict[str, np.ndarray]:
    """Raw 3DGS parameters -> exactly what Mitsuba's ``ellipsoids`` shape stores after loading our PLY.

    Inputs (raw, as in :class:`mi_gaussians.model.gaussians.Gaussians`): means (N, 3), scales (N, 3) log-sigma,
    rotations (N, 4) wxyz unnormalized, opacities (N,) logits, sh_dc (N, 3), sh_rest (N, K - 1, 3) or None.

    Returns float32 arrays: ``data`` (N, 10) ``[centre, max(exp(scale), 1e-6), normalized quat xyzw]``,
    ``opacities`` (N,) ``clip(sigmoid, 1e-8, 1 - 1e-8)``, ``sh_coeffs`` (N, 3K) coefficient-major RGB-interleaved.
    Activations are computed in float32 like the C++ loader (agreement to about 1 ulp; ``exp`` implementations may
    differ in the last bit). ``scale_factor`` / ``to_world`` of the shape are not applied (identity)."""
    means = np.asarray(means, np.float32).reshape(-1, 3)
    n = means.shape[0]
    scales = np.asarray(scales, np.float32).reshape(n, 3)
    rotations = np.asarray(rotations, np.float32).reshape(n, 4)
    opacities = np.asarray(opacities, np.float32).reshape(n)
    sh_dc = np.asarray(sh_dc, np.float32).reshape(n, 3)
    sh_rest = np.zeros((n, 0, 3), np.float32) if sh_rest is None else np.asarray(sh_rest, np.float32).reshape(n, -1, 3)
    sh_degree_from_coeff_count(sh_rest.shape[1] + 1)

    with np.errstate(over="ignore", under="ignore"):
        sigma = np.maximum(np.exp(scales), np.float32(ELLIPSOIDS_SIGMA_FLOOR))
        q = quat_wxyz_to_xyzw(rotations)
        with np.errstate(invalid="ignore", divide="ignore"):
            q = q / np.sqrt(np.sum(q * q, axis=1, keepdims=True, dtype=np.float32))
        alpha = np.float32(1.0) / (np.float32(1.0) + np.exp(-opacities))
    alpha = np.clip(alpha, np.float32(ELLIPSOIDS_OPACITY_CLIP[0]), np.float32(ELLIPSOIDS_OPACITY_CLIP[1]))
    data = np.concatenate([means, sigma, q], axis=1).astype(np.float32)
    sh = np.concatenate([sh_dc[:, None, :], sh_rest], axis=1).reshape(n, -1)
    return {"data": np.ascontiguousarray(data), "opacities": alpha.astype(np.float32),
            "sh_coeffs": np.ascontiguousarray(sh, dtype=np.float32)}


def from_ellipsoids_layout(data, opacities, sh_coeffs) -> dict[str, np.ndarray]:
    """Mitsuba ``ellipsoids`` storage -> raw 3DGS parameters (float32), the inverse of :func:`to_ellipsoids_layout`.

    ``data`` (N, 10) or flat (10 N), ``opacities`` (N,) / (N, 1), ``sh_coeffs`` (N, 3K) or flat. Returns the keys of
    ``Gaussians.from_numpy``: scales = log(sigma), rotations = (w, x, y, z) (unit length, as stored), opacities =
    logit(alpha) with alpha clipped to [1e-8, 1 - 1e-7] first (an alpha of exactly 1 has no finite logit).
    Exact inverse up to float rounding, except where the loader floored sigma or clipped alpha."""
    data = np.asarray(data, np.float32).reshape(-1, ELLIPSOID_STRUCT_SIZE)
    n = data.shape[0]
    alpha = np.asarray(opacities, np.float32).reshape(n)
    sh = np.asarray(sh_coeffs, np.float32).reshape(n, -1)
    if sh.shape[1] % 3:
        raise ValueError(f"sh_coeffs must hold 3 K values per ellipsoid, got {sh.shape[1]}")
    sh_degree_from_coeff_count(sh.shape[1] // 3)
    sigma = data[:, 3:6].astype(np.float64)
    if np.any(~(sigma > 0)):
        raise ValueError("ellipsoid sigma must be positive to take its logarithm")
    a = np.clip(alpha.astype(np.float64), 1e-8, 1.0 - 1e-7)
    sh3 = sh.reshape(n, -1, 3)
    return {
        "means": np.ascontiguousarray(data[:, 0:3]),
        "scales": np.log(sigma).astype(np.float32),
        "rotations": quat_xyzw_to_wxyz(data[:, 6:10]),
        "opacities": logit(a).astype(np.float32),
        "sh_dc": np.ascontiguousarray(sh3[:, 0, :]),
        "sh_rest": np.ascontiguousarray(sh3[:, 1:, :]),
    }


def ellipsoids_shape_dict(means, scales, rotations, opacities, sh_dc, sh_rest=None, **extra) -> dict:
    """A ``mi.load_dict`` dictionary for an ``ellipsoids`` shape holding these Gaussians (no file needed).

    Uses the shape's ``data`` path with 2-D tensors ``data`` (N, 10), ``opacities`` (N, 1) and ``sh_coeffs`` (N, 3K)
    from :func:`to_ellipsoids_layout`, so ``mi.traverse`` of the result matches loading the PLY we write.
    ``extra`` entries (e.g. ``extent=3.0``) are added as given. Needs a Mitsuba variant to be set."""
    from .drjit_utils import owned_tensor

    lay = to_ellipsoids_layout(means, scales, rotations, opacities, sh_dc, sh_rest)
    n = lay["data"].shape[0]
    d = {
        "type": "ellipsoids",
        "data": owned_tensor(lay["data"]),
        "opacities": owned_tensor(lay["opacities"].reshape(n, 1)),
        "sh_coeffs": owned_tensor(lay["sh_coeffs"]),
    }
    d.update(extra)
    return d


# The smallest image side a training or reference image may have (a resolution divisor or film size giving less is
# refused: a handful of pixels trains nothing)
MIN_IMAGE_SIDE = 16

#: Largest magnitude of a colour (SH) coefficient a model may hold. A trained model's are below ~10; at 1e12 the
#: colour of a degree-3 Gaussian stays below 0.5 + 16 * 1.1 * 1e12 ~ 1.8e13, whose sRGB decoding (x^2.4, for linear EXR
#: output) and square (SSIM) are still finite in float32. Larger values render Inf pixels, so models are refused.
MAX_ABS_SH_COEFFICIENT = 1e12
