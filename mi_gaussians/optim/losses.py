"""The 3DGS training loss, ``(1 - lambda) L1 + lambda (1 - SSIM)``, differentiable in Dr.Jit.

The image operators it is made of (L1, SSIM, their fused kernels and hand-written derivatives) live in
:mod:`mi_gaussians.image_ops`, which the evaluation metrics share; this module holds only the training rule.
"""

from __future__ import annotations

import mitsuba as mi

from ..image_ops import l1, weighted_l1_ssim


def photometric_loss(img: "mi.TensorXf", ref: "mi.TensorXf", lambda_dssim: float) -> "mi.Float":
    """The 3DGS training loss ``(1 - lambda) L1 + lambda (1 - SSIM)`` -> Float (1,).

    ``lambda_dssim`` comes from ``OptimConfig.lambda_dssim`` (0.2 in 3DGS). The L1 term rides in the SSIM kernels
    (:func:`mi_gaussians.image_ops.weighted_l1_ssim`), so the value and gradient equal those of
    ``(1 - lambda) * l1(img, ref) + lambda * d_ssim(img, ref)`` at the cost of SSIM alone."""
    lam = float(lambda_dssim)
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lambda_dssim must lie in [0, 1], got {lambda_dssim!r}")
    if lam == 0.0:
        return l1(img, ref)
    return weighted_l1_ssim(img, ref, 1.0 - lam, -lam, lam, 11, 1.5, 0.01 ** 2, 0.03 ** 2)
