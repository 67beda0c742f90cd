"""Helpers shared by the rasterizer tests: run our renderer on NumPy parameters, with or without gradients."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_gaussians as mig
from mi_gaussians.config import RasterConfig
from mi_gaussians.raster.rasterize import render

NAMES = ("means", "scales", "rotations", "opacities", "sh_dc", "sh_rest")


def render_numpy(params: dict, cam, background=(0.0, 0.0, 0.0), sh_degree=None, antialiased=False) -> dict:
    g = mig.Gaussians.from_numpy(**params)
    out = render(g, cam, background=background, sh_degree=sh_degree, cfg=RasterConfig(antialiased=antialiased))
    return {"rgb": np.array(out.rgb, dtype=np.float64).reshape(cam.height, cam.width, 3),
            "alpha": np.array(out.alpha, dtype=np.float64).reshape(cam.height, cam.width),
            "depth": np.array(out.depth, dtype=np.float64).reshape(cam.height, cam.width),
            "radii": np.array(out.radii), "out": out}


def random_weights(cam, seed=0, depth_scale=0.1) -> dict:
    rng = np.random.default_rng(seed)
    return {"rgb": rng.normal(size=(cam.height, cam.width, 3)), "alpha": rng.normal(size=(cam.height, cam.width)),
            "depth": rng.normal(size=(cam.height, cam.width)) * depth_scale}


def weighted_loss(out, weights: dict):
    return (dr.sum(out.rgb.array * mi.Float(weights["rgb"].astype(np.float32).ravel()))
            + dr.sum(out.alpha.array * mi.Float(weights["alpha"].astype(np.float32).ravel()))
            + dr.sum(out.depth.array * mi.Float(weights["depth"].astype(np.float32).ravel())))


def gradients_numpy(params: dict, cam, weights: dict, background=(0.0, 0.0, 0.0), sh_degree=None, antialiased=False,
                    cfg: RasterConfig | None = None):
    """Our gradients of the weighted loss w.r.t. every raw parameter, plus the render output (with ``cfg``, that
    configuration instead of the default's ``antialiased`` variant)."""
    g = mig.Gaussians.from_numpy(**params)
    for k in NAMES:
        dr.enable_grad(getattr(g, k))
    cfg = RasterConfig(antialiased=antialiased) if cfg is None else cfg
    out = render(g, cam, background=background, sh_degree=sh_degree, cfg=cfg)
    dr.backward(weighted_loss(out, weights))
    grads = {k: (np.array(dr.grad(getattr(g, k)), dtype=np.float64).reshape(params[k].shape) if params[k].size
                 else np.zeros(params[k].shape)) for k in NAMES}
    return grads, out
