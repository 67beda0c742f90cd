"""How much each Gaussian shows in the training views: its blending weight, exactly, through the renderer.

A Gaussian's weight in a view is the sum over the view's pixels of ``T * alpha`` (the share of each pixel's colour it
gives). It is measured without a new kernel: the model is rendered with every colour 1 (SH degree 0, nothing
clamped), and the gradient of the image's sum with respect to a Gaussian's DC coefficient is ``SH_C0`` times its
weight, per channel. :func:`max_weights` keeps, per Gaussian, the largest over a list of cameras of its weight divided
by the view's pixel count: "the share of the image it gives in the view that sees it most", which does not depend on
the image size (a rule in pixels would: the same Gaussian covers four times the pixels of an image twice as wide).
``densify.weight_prune`` removes the Gaussians below a threshold at the end of densification
(:class:`~mi_gaussians.optim.densify.DefaultStrategy`). Measured offline on trained models
(``benchmarks/prune_scores.py``, docs/benchmarks/work_per_step.md): 10-15 % of the Gaussians of the shared objects'
models are seen by no training view, and their removal changes no test score. ``densify.prune_unseen`` removes
those: a weight below the renderer's own cut-off (``raster.alpha_min``, 1/255) of one pixel in every training view
(``unit="pixels"``: "seen by no view" is a property of the pixels, whatever the image size).

:func:`error_weights` weighs the same quantity by a mask of each view's high-error pixels: FastGS's densification
score (``densify.error_gate``), which densifies only where several views agree that the image is not yet fitted.
"""

from __future__ import annotations

from typing import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import RasterConfig
from ..conventions import SH_C0
from ..drjit_utils import owned_tensor
from ..model.gaussians import Gaussians
from ..raster.rasterize import render


def max_weights(g: Gaussians, cameras: Sequence, cfg: RasterConfig = RasterConfig(), unit: str = "share") -> "mi.Float":
    """Per Gaussian of ``g``, its largest blending weight over ``cameras``: with ``unit="share"`` each divided by its
    camera's pixel count (a share of the image: N values in [0, 1]), with ``unit="pixels"`` as it is (pixels' worth
    of colour)."""
    if unit not in ("share", "pixels"):
        raise ValueError(f"max_weights: unit must be 'share' or 'pixels', got {unit!r}")
    best = dr.zeros(mi.Float, g.n)
    if g.n == 0:
        return best
    for camera in cameras:
        scale = 1.0 / (camera.width * camera.height) if unit == "share" else 1.0
        best = dr.maximum(best, _probe_weights(g, camera, None, cfg) * scale)
        dr.eval(best)
    return best


def _channel_sum(rgb: "mi.Float") -> "mi.Float":
    """The sum of each (r, g, b) triple of an interleaved array: one value per pixel or per Gaussian."""
    v = dr.unravel(mi.Vector3f, rgb)
    return v.x + v.y + v.z


def _probe_weights(g: Gaussians, camera, pixel_weight, cfg: RasterConfig) -> "mi.Float":
    """Per Gaussian, the sum over ``camera``'s pixels of ``pixel_weight * T * alpha`` (``pixel_weight``: (H, W) values,
    or None for 1), through the renderer's backward pass on a probe model whose every colour is 1."""
    n = g.n
    white = dr.full(mi.Float, 0.5 / SH_C0, 3 * n)
    no_rest = owned_tensor(np.zeros((n, 0, 3), np.float32))
    dc = mi.TensorXf(white, (n, 3))
    dr.enable_grad(dc)
    probe = Gaussians(means=dr.detach(g.means), scales=dr.detach(g.scales), rotations=dr.detach(g.rotations),
                      opacities=dr.detach(g.opacities), sh_dc=dc, sh_rest=no_rest)
    out = render(probe, camera, background=(0.0, 0.0, 0.0), sh_degree=0, cfg=cfg, depth=False)
    rgb = out.rgb.array
    if pixel_weight is not None:
        rgb = rgb * dr.repeat(pixel_weight, 3)
    dr.backward(dr.sum(rgb))
    return _channel_sum(dr.grad(dc).array) * (1.0 / (3.0 * SH_C0))


def error_weights(g: Gaussians, views: Sequence, sh_degree: int, background, threshold: float,
                  cfg: RasterConfig = RasterConfig()) -> "mi.Float":
    """Per Gaussian of ``g``, its mean over ``views`` ((camera, target (H, W, 3)) pairs) of its blending weight in
    the view's high-error pixels, as a share of the view's pixels: a pixel is high-error where its L1 error (the mean
    over the channels), rescaled to [0, 1] between the view's smallest and largest, exceeds ``threshold`` (FastGS's
    multi-view consistent densification score, with each pixel weighted by the Gaussian's ``T * alpha`` there
    instead of counted)."""
    n = g.n
    total = dr.zeros(mi.Float, n)
    if n == 0 or not views:
        return total
    for camera, target in views:
        with dr.suspend_grad():
            out = render(g, camera, background=background, sh_degree=sh_degree, cfg=cfg, depth=False)
            npix = camera.width * camera.height
            e = _channel_sum(dr.abs(out.rgb.array - target.array))
            lo, hi = dr.min(e), dr.max(e)
            mask = dr.select((e - lo) > threshold * (hi - lo), 1.0, 0.0)
            dr.eval(mask)
        total += _probe_weights(g, camera, mask, cfg) * (1.0 / npix)
        dr.eval(total)
    return total * (1.0 / len(views))
