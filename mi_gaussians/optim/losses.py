"""The 3DGS training loss, ``(1 - lambda) L1 + lambda (1 - SSIM)``, differentiable in Dr.Jit.

The image operators it is made of (L1, SSIM, their fused kernels and hand-written derivatives) live in
:mod:`mi_gaussians.image_ops`, which the evaluation metrics share; this module holds only the training rule.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..image_ops import l1, weighted_l1_ssim


def photometric_loss(img: "mi.TensorXf", ref: "mi.TensorXf", lambda_dssim: float) -> "mi.Float":
    """The 3DGS training loss ``(1 - lambda) L1 + lambda (1 - SSIM)`` -> Float (1,).

    ``lambda_dssim`` comes from ``OptimConfig.lambda_dssim`` (0.2 in 3DGS); SSIM is the reference's
    (:data:`mi_gaussians.image_ops.REFERENCE_SSIM`). The L1 term rides in the SSIM kernels
    (:func:`mi_gaussians.image_ops.weighted_l1_ssim`), so the value and gradient equal those of
    ``(1 - lambda) * l1(img, ref) + lambda * d_ssim(img, ref)`` at the cost of SSIM alone."""
    lam = float(lambda_dssim)
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lambda_dssim must lie in [0, 1], got {lambda_dssim!r}")
    if lam == 0.0:
        return l1(img, ref)
    return weighted_l1_ssim(img, ref, l1_weight=1.0 - lam, ssim_weight=-lam, offset=lam)


def inverse_depth_target(depth) -> "np.ndarray":
    """The target of :func:`depth_loss` from an exact depth map (H, W): 1 / depth where a surface was hit, 0 where
    not (+inf, 0 or non-finite depth)."""
    import numpy as np

    d = np.asarray(depth, np.float64)
    hit = np.isfinite(d) & (d > 0)
    out = np.zeros(d.shape, np.float32)
    out[hit] = 1.0 / d[hit]
    return out


def depth_loss(depth: "mi.TensorXf", alpha: "mi.TensorXf", inv_target: "mi.TensorXf") -> "mi.Float":
    """Inverse-depth L1 against exact depth -> Float (1,): the mean over all pixels of ``|1 / depth - inv_target|``
    where the target saw a surface (``inv_target > 0``) and the render covers the pixel (alpha > 0.5), 0 elsewhere
    (the 2024 reference's ``|invDepth - mono_invdepth| * depth_mask``, with exact depth for the monocular estimate).
    ``depth`` and ``alpha`` are the render's expected depth and coverage (H, W); the gradient flows through both
    parts of ``depth`` = sum(z w) / sum(w)."""
    d, r = depth.array, inv_target.array
    valid = (r > 0.0) & (dr.detach(alpha.array) > 0.5) & (dr.detach(d) > 0.0)
    inv = dr.rcp(dr.select(valid, d, 1.0))
    return dr.mean(dr.select(valid, dr.abs(inv - r), 0.0))
