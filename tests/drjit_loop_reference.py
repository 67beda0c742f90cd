"""A second, independent backward: Dr.Jit's own reverse-mode AD through a brute-force per-pixel loop.

Every pixel walks all Gaussians in global depth order (no tiles, no footprints, no CustomOp) with the reference
blending rules; ``dr.while_loop(..., max_iterations=N)`` lets Dr.Jit record the loop for reverse-mode AD. The
projection is the library's (plain Dr.Jit AD, itself checked against finite differences), so this isolates the
hand-written blend backward.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_gaussians as mig
from mi_gaussians.config import RasterConfig
from mi_gaussians.drjit_utils import fmin
from mi_gaussians.raster.projection import GaussianArrays, ViewParams, project

NAMES = ("means", "scales", "rotations", "opacities", "sh_dc", "sh_rest")


def loop_ad_render(params: dict, cam, weights: dict, background=(0.0, 0.0, 0.0), view: ViewParams | None = None,
                   cfg: RasterConfig = RasterConfig()):
    """The weighted loss's gradients with respect to the Gaussians (and, through ``view``, a camera's own Dr.Jit
    parameters: pass a view made from values with gradients enabled, and read them after the call; default: the view
    of ``cam``), and the image; ``cfg``: the blending rules' thresholds (``alpha_min`` ...)."""
    g = mig.Gaussians.from_numpy(**params)
    for k in NAMES:
        dr.enable_grad(getattr(g, k))
    proj = project(GaussianArrays.from_gaussians(g, g.sh_degree), ViewParams.from_camera(cam) if view is None else view,
                   cfg)
    valid = np.array(proj.tile_count) > 0
    depth = np.array(dr.detach(proj.depth))
    order_np = np.array([i for i in np.argsort(depth, kind="stable") if valid[i]], dtype=np.uint32)
    order = mi.UInt32(order_np)
    m = len(order_np)
    W, H = cam.width, cam.height
    pix = dr.arange(mi.UInt32, W * H)
    py = mi.Float(pix // W) + 0.5
    px = mi.Float(pix % W) + 0.5

    def cond(i, T, C, D, done):
        return (i < m) & ~done

    def body(i, T, C, D, done):
        gi = dr.gather(mi.UInt32, order, i)
        mx = dr.gather(mi.Float, proj.mean2d.x, gi)
        my = dr.gather(mi.Float, proj.mean2d.y, gi)
        ca = dr.gather(mi.Float, proj.conic.x, gi)
        cb = dr.gather(mi.Float, proj.conic.y, gi)
        cc = dr.gather(mi.Float, proj.conic.z, gi)
        op = dr.gather(mi.Float, proj.opacity, gi)
        z = dr.gather(mi.Float, proj.depth, gi)
        col = dr.gather(mi.Color3f, proj.color, gi)
        dx, dy = mx - px, my - py
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        alpha = fmin(op * dr.exp(power), cfg.alpha_max)
        hit = (alpha >= cfg.alpha_min) & (power <= 0)
        test_T = T * (1.0 - alpha)
        stop = hit & (test_T < cfg.transmittance_min)
        hit = hit & ~stop
        w = alpha * T
        C = dr.select(hit, C + col * w, C)
        D = dr.select(hit, D + z * w, D)
        T = dr.select(hit, test_T, T)
        return i + 1, T, C, D, done | stop

    state = (dr.zeros(mi.UInt32, W * H), dr.full(mi.Float, 1.0, W * H), dr.zeros(mi.Color3f, W * H),
             dr.zeros(mi.Float, W * H), dr.full(mi.Bool, False, W * H))
    _, T, C, D, _ = dr.while_loop(state, cond, body, max_iterations=max(m, 1))
    bg = mi.Color3f(*background)
    rgb = C + T * bg
    alpha = 1.0 - T
    depth_img = dr.select(alpha > 1e-12, D / dr.select(alpha > 1e-12, alpha, 1.0), 0.0)
    wr = mi.Color3f(*[mi.Float(weights["rgb"][..., c].astype(np.float32).ravel()) for c in range(3)])
    loss = (dr.sum(dr.dot(rgb, wr)) + dr.sum(alpha * mi.Float(weights["alpha"].astype(np.float32).ravel()))
            + dr.sum(depth_img * mi.Float(weights["depth"].astype(np.float32).ravel())))
    dr.backward(loss)
    grads = {k: (np.array(dr.grad(getattr(g, k)), dtype=np.float64).reshape(params[k].shape) if params[k].size
                 else np.zeros(params[k].shape)) for k in NAMES}
    img = {"rgb": np.stack([np.array(rgb[c]) for c in range(3)], -1).reshape(H, W, 3)}
    return grads, img
