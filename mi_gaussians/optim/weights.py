"""How much each Gaussian shows in the training views: its blending weight, exactly, through the renderer.

A Gaussian's weight in a view is the sum over the view's pixels of ``T * alpha`` (the share of each pixel's colour it
gives). It is measured without a new kernel: the model is rendered with every colour 1 (SH degree 0, nothing
clamped), and the gradient of the image's sum with respect to a Gaussian's DC coefficient is ``SH_C0`` times its
weight, per channel. :func:`max_weights` keeps, per Gaussian, the largest over a list of cameras of its weight divided
by the view's pixel count: "the share of the image it gives in the view that sees it most", which does not depend on
the image size (a rule in pixels would: the same Gaussian covers four times the pixels of an image twice as wide).
``densify.weight_prune`` removes the Gaussians below a threshold at the end of densification
(:class:`~mi_gaussians.optim.densify.DefaultStrategy`). Measured offline on trained models
(``benchmarks/prune_scores.py``, docs/benchmarks/work_per_step.md): 10-14 % of the Gaussians of the shared objects'
models are seen by no training view, and their removal changes no test score.
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


def max_weights(g: Gaussians, cameras: Sequence, cfg: RasterConfig = RasterConfig()) -> "mi.Float":
    """Per Gaussian of ``g``, its largest blending weight over ``cameras``, each divided by its camera's pixel count
    (a share of the image: N values in [0, 1])."""
    n = g.n
    best = dr.zeros(mi.Float, n)
    if n == 0:
        return best
    white = dr.full(mi.Float, 0.5 / SH_C0, 3 * n)
    no_rest = owned_tensor(np.zeros((n, 0, 3), np.float32))
    idx = dr.arange(mi.UInt32, n) * 3
    for camera in cameras:
        dc = mi.TensorXf(mi.Float(white), (n, 3))
        dr.enable_grad(dc)
        probe = Gaussians(means=dr.detach(g.means), scales=dr.detach(g.scales), rotations=dr.detach(g.rotations),
                          opacities=dr.detach(g.opacities), sh_dc=dc, sh_rest=no_rest)
        out = render(probe, camera, background=(0.0, 0.0, 0.0), sh_degree=0, cfg=cfg)
        dr.backward(dr.sum(out.rgb.array))
        grad = dr.grad(dc).array
        w = (dr.gather(mi.Float, grad, idx) + dr.gather(mi.Float, grad, idx + 1)
             + dr.gather(mi.Float, grad, idx + 2)) * (1.0 / (3.0 * SH_C0 * camera.width * camera.height))
        best = dr.maximum(best, w)
        dr.eval(best)
    return best
