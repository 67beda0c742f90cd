"""The 3DGS training loss, ``(1 - lambda) L1 + lambda (1 - SSIM)``, differentiable in Dr.Jit.

The image operators it is made of (L1, SSIM, their fused kernels and hand-written derivatives) live in
:mod:`mi_gaussians.image_ops`, which the evaluation metrics share; this module holds only the training rule.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..config import SSIM_PADDINGS
from ..drjit_utils import flat_mean
from ..image_ops import REFERENCE_SSIM, l1, ssim_map, weighted_l1_ssim


def photometric_loss(img: "mi.TensorXf", ref: "mi.TensorXf", lambda_dssim: float,
                     ssim_padding: str = "same") -> "mi.Float":
    """The 3DGS training loss ``(1 - lambda) L1 + lambda (1 - SSIM)`` -> Float (1,).

    ``lambda_dssim`` comes from ``OptimConfig.lambda_dssim`` (0.2 in 3DGS); SSIM is the reference's
    (:data:`mi_gaussians.image_ops.REFERENCE_SSIM`), averaged over the image (``ssim_padding="same"``) or over its
    valid region (``"valid"``, gsplat's trainer: :func:`valid_ssim`). With "same" the L1 term rides in the SSIM kernels
    (:func:`mi_gaussians.image_ops.weighted_l1_ssim`), so the value and gradient equal those of
    ``(1 - lambda) * l1(img, ref) + lambda * d_ssim(img, ref)`` at the cost of SSIM alone."""
    lam = float(lambda_dssim)
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lambda_dssim must lie in [0, 1], got {lambda_dssim!r}")
    if ssim_padding not in SSIM_PADDINGS:
        raise ValueError(f"ssim_padding must be one of {', '.join(SSIM_PADDINGS)}, got {ssim_padding!r}")
    if lam == 0.0:
        return l1(img, ref)
    if ssim_padding == "valid":
        return (1.0 - lam) * l1(img, ref) + lam * (1.0 - valid_ssim(img, ref))
    return weighted_l1_ssim(img, ref, l1_weight=1.0 - lam, ssim_weight=-lam, offset=lam)


def valid_ssim(img: "mi.TensorXf", ref: "mi.TensorXf") -> "mi.Float":
    """Mean SSIM over the valid region of (H, W, C) images -> Float (1,): the pixels at least ``window // 2`` from
    every edge, whose window never reaches the zero padding (gsplat's ``fused_ssim(..., padding="valid")``, the
    mean of a "valid" convolution). Differentiable through :func:`mi_gaussians.image_ops.ssim_map`."""
    H, W = int(img.shape[0]), int(img.shape[1])
    C = int(img.shape[2]) if len(img.shape) == 3 else 1
    r = REFERENCE_SSIM.window // 2
    if H <= 2 * r or W <= 2 * r:
        raise ValueError(f"an SSIM over the valid region needs images larger than {2 * r} pixels a side, got {W}x{H}")
    m = ssim_map(img, ref).array
    UInt = dr.uint32_array_t(type(m))
    i = dr.arange(UInt, H * W * C)
    y, x = i // (W * C), (i // C) % W
    inside = (y >= r) & (y < H - r) & (x >= r) & (x < W - r)
    return dr.sum(dr.select(inside, m, 0.0)) * (1.0 / ((H - 2 * r) * (W - 2 * r) * C))


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
    return flat_mean(dr.select(valid, dr.abs(inv - r), 0.0))


def alpha_loss(alpha: "mi.TensorXf", transparency: "mi.TensorXf") -> "mi.Float":
    """Mean absolute difference of a render's alpha ((H, W), ``out.alpha``) from a target's alpha given as its
    transparency ((H, W, 1), 1 - alpha) -> Float (1,)."""
    h, w = int(alpha.shape[0]), int(alpha.shape[1])
    return l1(mi.TensorXf(alpha.array, (h, w, 1)), 1.0 - transparency)
