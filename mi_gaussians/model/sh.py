"""View-dependent colour from spherical harmonics, exactly as the reference CUDA ``computeColorFromSH``.

``colour = max(C0 sh0 + sum_{l, m} Y_lm(dir) sh_lm + 0.5, 0)`` with ``dir = normalize(mean - camera_centre)`` and the
reference's real SH basis, constants and signs (degree <= 3)::

    Y_00 = C0
    Y_1  = -C1 y,  C1 z,  -C1 x
    Y_2  = C2[0] xy, C2[1] yz, C2[2] (2zz - xx - yy), C2[3] xz, C2[4] (xx - yy)
    Y_3  = C3[0] y (3xx - yy), C3[1] xy z, C3[2] y (4zz - xx - yy), C3[3] z (2zz - 3xx - 3yy),
           C3[4] x (4zz - xx - yy), C3[5] z (xx - yy), C3[6] x (xx - 3yy)

Relation to Dr.Jit: ``dr.sh_eval(dir, degree)`` returns exactly this basis, same order, same signs (verified to float
precision in ``tests/test_conventions.py``), so the reference SH coefficients can be used with ``dr.sh_eval`` directly
(as Mitsuba's ``volprim_rf_basic`` does with 3DGS PLYs).

Clamp: implemented as ``dr.select(c < 0, 0, c)`` (never ``dr.maximum``, which aborts with libLLVM 15). Its gradient
is zero where ``c < 0`` and passes unchanged where ``c >= 0`` -- the reference's ``clamped = result < 0`` rule.
"""

from __future__ import annotations

from typing import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from ..conventions import SH_C0, sh_coeff_count
from ..drjit_utils import row_vectors

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def _check_degree(degree, n_rest: int) -> int:
    if not isinstance(degree, (int, np.integer)) or not 0 <= int(degree) <= 3:
        raise ValueError(f"SH degree must be an integer in 0..3, got {degree!r}")
    need = sh_coeff_count(degree) - 1
    if n_rest < need:
        raise ValueError(f"active SH degree {int(degree)} needs {need} higher-band coefficients, only {n_rest} stored")
    return int(degree)


# ---------------------------------------------------------------------------------------------------- Dr.Jit
def sh_basis(dirs, degree: int) -> list:
    """The reference real SH basis at unit directions ``dirs`` (mi.Vector3f): a list of (degree + 1)^2 Float.

    Plain Dr.Jit arithmetic (differentiable). Equal to ``dr.sh_eval(dirs, degree)``."""
    degree = _check_degree(degree, 15)
    x, y, z = dirs.x, dirs.y, dirs.z
    out = [dr.full(type(x), SH_C0, dr.width(x))]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
        if degree >= 3:
            out += [
                SH_C3[0] * y * (3.0 * xx - yy),
                SH_C3[1] * xy * z,
                SH_C3[2] * y * (4.0 * zz - xx - yy),
                SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                SH_C3[4] * x * (4.0 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3.0 * yy),
            ]
    return out


def eval_sh_colors(sh_dc, sh_rest: Sequence, dirs, degree: int, *, normalize: bool = True, clamp: bool = True):
    """RGB colour per lane: ``max(SH(dir) + 0.5, 0)`` with the reference basis; AD-differentiable.

    sh_dc: mi.Vector3f / mi.Color3f, the DC coefficients (one lane per Gaussian);
    sh_rest: sequence of mi.Vector3f / mi.Color3f, the higher-band coefficients in band order (index 0 = Y_1,-1),
        at least (degree + 1)^2 - 1 of them (extra ones, of a higher stored degree, are ignored);
    dirs: mi.Vector3f, ``mean - camera_centre`` (normalized here unless ``normalize=False``; AD flows through);
    degree: active SH degree 0..3 (<= the stored degree).
    Returns a 3-vector of the coefficients' type (mi.Vector3f for :func:`gather_sh_coeffs` output), clamped at 0 with
    zero gradient where the unclamped value is negative (``clamp=False``: the unclamped value)."""
    degree = _check_degree(degree, len(sh_rest))
    d = dr.normalize(dirs) if normalize else dirs
    basis = sh_basis(d, degree)
    c = SH_C0 * sh_dc
    for i in range(1, len(basis)):
        c = c + basis[i] * sh_rest[i - 1]
    c = c + 0.5
    return dr.select(c < 0, 0.0, c) if clamp else c


def sh_dir_grad(dirs, degree: int, weights: Sequence) -> "mi.Vector3f":
    """``sum_i weights[i - 1] grad Y_i(dirs)`` over the basis functions of degree 1 to ``degree`` (``weights``: one
    Float per function, in the order of :func:`sh_basis` without Y_00): the gradient of the basis' polynomials in
    (x, y, z) at ``dirs``, as the reference's ``computeColorFromSH`` backward takes it (before the normalization)."""
    degree = _check_degree(degree, len(weights))
    x, y, z = dirs.x, dirs.y, dirs.z
    w = list(weights)
    zero = dr.zeros(type(x), 1)
    gx, gy, gz = zero, zero, zero
    if degree >= 1:
        gx = gx - SH_C1 * w[2]
        gy = gy - SH_C1 * w[0]
        gz = gz + SH_C1 * w[1]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        c0, c1, c2, c3, c4 = (SH_C2[0] * w[3], SH_C2[1] * w[4], SH_C2[2] * w[5], SH_C2[3] * w[6],
                              SH_C2[4] * w[7])
        gx = gx + c0 * y - 2.0 * c2 * x + c3 * z + 2.0 * c4 * x
        gy = gy + c0 * x + c1 * z - 2.0 * c2 * y - 2.0 * c4 * y
        gz = gz + c1 * y + 4.0 * c2 * z + c3 * x
        if degree >= 3:
            k = [SH_C3[i] * w[8 + i] for i in range(7)]
            gx = gx + (6.0 * k[0] * xy + k[1] * yz - 2.0 * k[2] * xy - 6.0 * k[3] * xz
                       + k[4] * (4.0 * zz - 3.0 * xx - yy) + 2.0 * k[5] * xz + k[6] * (3.0 * xx - 3.0 * yy))
            gy = gy + (k[0] * (3.0 * xx - 3.0 * yy) + k[1] * xz + k[2] * (4.0 * zz - xx - 3.0 * yy)
                       - 6.0 * k[3] * yz - 2.0 * k[4] * xy - 2.0 * k[5] * yz - 6.0 * k[6] * xy)
            gz = gz + (k[1] * xy + 8.0 * k[2] * yz + k[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) + 8.0 * k[4] * xz
                       + k[5] * (xx - yy))
    return mi.Vector3f(gx, gy, gz)


def gather_sh_coeffs(sh_dc: "mi.TensorXf", sh_rest: "mi.TensorXf", degree: int, index=None):
    """Per-lane SH coefficients from the model tensors, for :func:`eval_sh_colors`.

    sh_dc (N, 3) and sh_rest (N, K - 1, 3) tensors (coefficient-major, as in ``Gaussians``); ``index`` (mi.UInt32,
    default all N) selects the Gaussians. Only the coefficients of the active ``degree`` are gathered. Returns
    ``(dc, rest)``: a mi.Vector3f and a list of (degree + 1)^2 - 1 mi.Vector3f. Differentiable w.r.t. the tensors."""
    k_rest = int(sh_rest.shape[1]) if len(sh_rest.shape) == 3 else 0
    degree = _check_degree(degree, k_rest)
    if index is None:
        # All Gaussians once each: the reverse mode writes the gradients with plain scatters (row_vectors)
        rest = row_vectors(mi.Vector3f, sh_rest.array, k_rest, sh_coeff_count(degree) - 1) if k_rest else []
        return row_vectors(mi.Vector3f, sh_dc.array)[0], rest
    dc = dr.gather(mi.Vector3f, sh_dc.array, index)
    rest = [dr.gather(mi.Vector3f, sh_rest.array, index * k_rest + j) for j in range(sh_coeff_count(degree) - 1)]
    return dc, rest
