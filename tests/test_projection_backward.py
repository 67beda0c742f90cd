"""The projection's hand-written reverse mode (raster/projection_backward.py) against Dr.Jit's AD of the same forward
code (``render_arrays`` of ``GaussianArrays.from_gaussians``, the reference it replaces): the same images bit for bit
and the gradients of every raw parameter equal up to float rounding, on every scene of tests/scene_factory.py
(degenerate ones included), anti-aliased or not, at an active SH degree below the stored one, with only some tables
carrying gradients, and on a scene built to take every branch (colours clamped at 0, means beyond the guard band,
Gaussians behind the camera, near-zero quaternions). The finite-difference tests of tests/test_raster.py go through
this path too (``render``)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
import scene_factory as sf
from mi_gaussians.config import RasterConfig
from mi_gaussians.raster.projection import GaussianArrays, ViewParams
from mi_gaussians.raster.projection_backward import uses_hand_written_backward
from mi_gaussians.raster.rasterize import render, render_arrays
from raster_helpers import NAMES, random_weights, weighted_loss

BACKGROUND = (0.3, 0.5, 0.7)
RTOL = 1e-4    # of the largest gradient of each table (float32 sums in another order; measured: at most 5e-6)


def _gradients(params, cam, cfg, hand_written: bool, degree=None, enabled=NAMES):
    g = mig.Gaussians.from_numpy(**params)
    for k in enabled:
        dr.enable_grad(getattr(g, k))
    deg = g.sh_degree if degree is None else degree
    view = ViewParams.from_camera(cam)
    if hand_written:
        assert uses_hand_written_backward(g, view)
        out = render(g, view, background=BACKGROUND, sh_degree=deg, cfg=cfg)
    else:
        out = render_arrays(GaussianArrays.from_gaussians(g, deg), view, background=BACKGROUND, cfg=cfg)
    dr.backward(weighted_loss(out, random_weights(cam, seed=1, depth_scale=1.0)),
                flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    result = {k: np.array(dr.grad(getattr(g, k)), dtype=np.float64) for k in enabled}
    result["rgb"] = np.array(out.rgb)
    result["means2d_grad"] = np.array(out.means2d_grad, dtype=np.float64)
    return result


def _assert_same(ours, ref):
    np.testing.assert_array_equal(ours["rgb"], ref["rgb"])
    for k in ref:
        if k == "rgb" or ref[k].size == 0:
            continue
        assert np.all(np.isfinite(ours[k])), k
        scale = max(float(np.abs(ref[k]).max()), 1e-30)
        np.testing.assert_allclose(ours[k], ref[k], rtol=0, atol=RTOL * scale, err_msg=k)


def branches(seed: int = 0):
    """Every branch of the reverse mode: SH colours below 0 (clamped), means beyond the guard band (the Jacobian's
    coordinates clamped), Gaussians behind the camera and on the near plane, near-zero and huge quaternions."""
    rng = np.random.default_rng(seed)
    cam = sf.generic_camera(48, 40)
    n = 120
    depth = rng.uniform(0.5, 6.0, n)
    depth[:10] = rng.uniform(-2.0, 0.2, 10)                     # behind the camera and at the near plane
    px, py = rng.uniform(-0.6, 1.6, n) * cam.width, rng.uniform(-0.6, 1.6, n) * cam.height   # past the guard band
    means = sf.pixel_to_world(cam, px, py, np.abs(depth) + 0.05)
    means[:10] = sf.pixel_to_world(cam, px[:10], py[:10], depth[:10] + 1e-3 * np.sign(depth[:10]))
    scales = np.log(rng.uniform(0.02, 0.6, (n, 3)))
    quats = sf.random_quaternions(rng, n)
    quats[10:15] *= 1e-13                                        # below the normalization's floor
    quats[15:20] *= 1e6
    dc, rest = sf.random_sh(rng, n, 3, dc_scale=2.0, rest_scale=0.6)   # many colours below 0
    params = sf.make_params(means, scales, quats, sf.logit(rng.uniform(0.01, 0.99, n)), dc, rest, sh_degree=3)
    return params, cam


SCENES = {**sf.SCENES, "branches": branches}


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("name", sorted(SCENES))
def test_the_hand_written_backward_equals_ad(name, antialiased, ordered_sums):
    params, cam = SCENES[name](seed=0)
    if params["means"].shape[0] == 0:
        pytest.skip("no Gaussians: nothing is projected")
    cfg = RasterConfig(antialiased=antialiased)
    _assert_same(_gradients(params, cam, cfg, True), _gradients(params, cam, cfg, False))


def test_the_branch_scene_takes_every_branch():
    """The scene above reaches what it says (otherwise the test of it would pass without testing them)."""
    from mi_gaussians.model.sh import eval_sh_colors, gather_sh_coeffs
    from mi_gaussians.raster.projection import guard_limits

    params, cam = branches()
    g = mig.Gaussians.from_numpy(**params)
    view = ViewParams.from_camera(cam)
    w2c = np.asarray(cam.world_to_camera)
    t = params["means"] @ w2c[:3, :3].T + w2c[:3, 3]
    cfg = RasterConfig()
    lims = [float(v[0]) for v in guard_limits(view, cfg)]
    u, v = t[:, 0] / t[:, 2], t[:, 1] / t[:, 2]
    front = t[:, 2] > cfg.near_plane
    assert (~front).sum() >= 5 and front.sum() >= 50
    assert np.sum(front & ((u < lims[0]) | (u > lims[1]) | (v < lims[2]) | (v > lims[3]))) >= 10
    dc, rest = gather_sh_coeffs(g.sh_dc, g.sh_rest, 3)
    d = mi.Vector3f(*[mi.Float(c) for c in (params["means"] - cam.center).T])
    c = np.array(eval_sh_colors(dc, rest, d, 3, clamp=False))
    assert np.sum(c < 0) >= 20 and np.sum(c > 0) >= 20


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_an_active_degree_below_the_stored_one(degree, ordered_sums):
    params, cam = branches(seed=1)
    cfg = RasterConfig()
    ours, ref = _gradients(params, cam, cfg, True, degree), _gradients(params, cam, cfg, False, degree)
    _assert_same(ours, ref)
    inactive = ours["sh_rest"].reshape(-1, 15, 3)[:, (degree + 1) ** 2 - 1:]
    assert np.all(inactive == 0)


@pytest.mark.parametrize("enabled", [("sh_dc",), ("opacities", "scales"), ("means", "rotations", "sh_rest")])
def test_only_the_tables_that_carry_gradients(enabled, ordered_sums):
    """As the blending-weight probe does (optim/weights.py: the DC colours only)."""
    params, cam = sf.random_scene(2, n=60, sh_degree=2)
    cfg = RasterConfig()
    _assert_same(_gradients(params, cam, cfg, True, enabled=enabled),
                 _gradients(params, cam, cfg, False, enabled=enabled))


@pytest.mark.parametrize("name", ["random_deg3", "branches", "border_and_outside"])
def test_the_pose_gradients_equal_ad(name, ordered_sums):
    """A pose correction moves the view differentiably (--pose-opt): the gradients of its rotation, translation and
    centre (sums over the Gaussians), and with them the tables', equal AD's."""
    params, cam = SCENES[name](seed=0)
    grads = []
    for hand_written in (True, False):
        g = mig.Gaussians.from_numpy(**params)
        view = ViewParams.from_camera(cam)
        for v in (g.means, g.sh_dc, view.R, view.t, view.center):
            dr.enable_grad(v)
        assert uses_hand_written_backward(g, view)
        out = render(g, view, background=BACKGROUND, cfg=RasterConfig()) if hand_written else \
            render_arrays(GaussianArrays.from_gaussians(g, g.sh_degree), view, background=BACKGROUND)
        dr.backward(weighted_loss(out, random_weights(cam, seed=1, depth_scale=1.0)))
        grads.append({"R": np.array([[dr.grad(view.R)[i][j][0] for j in range(3)] for i in range(3)], np.float64),
                      "t": np.array([dr.grad(view.t)[i][0] for i in range(3)], np.float64),
                      "center": np.array([dr.grad(view.center)[i][0] for i in range(3)], np.float64),
                      "means": np.array(dr.grad(g.means), np.float64), "sh_dc": np.array(dr.grad(g.sh_dc), np.float64)})
    for k, ref in grads[1].items():
        assert np.abs(ref).max() > 0, k
        np.testing.assert_allclose(grads[0][k], ref, rtol=0, atol=RTOL * np.abs(ref).max(), err_msg=k)


def test_which_path_a_render_takes():
    """No gradients: the plain forward; the model's tables or the view's pose: the hand-written reverse mode; the
    intrinsics (which nothing here trains): AD."""
    params, cam = sf.random_scene(0, n=20)
    g = mig.Gaussians.from_numpy(**params)
    view = ViewParams.from_camera(cam)
    assert not uses_hand_written_backward(g, view)
    dr.enable_grad(view.t)
    assert uses_hand_written_backward(g, view)
    dr.enable_grad(g.means)
    assert uses_hand_written_backward(g, view)
    dr.enable_grad(view.fx)
    assert not uses_hand_written_backward(g, view)


def test_what_no_gradient_reaches_gets_zeros_as_from_ad():
    """A non-finite view (a diverged pose correction) culls every Gaussian, and their intermediates are NaN: AD scales
    no derivative by a zero gradient, so their gradients are zeros, and so are ours (0 * NaN would be NaN)."""
    import dataclasses

    params, cam = sf.random_scene(0, n=30, sh_degree=1)
    grads = []
    for hand_written in (True, False):
        g = mig.Gaussians.from_numpy(**params)
        for k in NAMES:
            dr.enable_grad(getattr(g, k))
        view = ViewParams.from_camera(cam)
        nan = mi.Float(float("nan"))
        dr.enable_grad(nan)
        view = dataclasses.replace(view, R=mi.Matrix3f([[view.R[i][j] + nan for j in range(3)] for i in range(3)]),
                                   t=view.t + nan)
        assert uses_hand_written_backward(g, view)
        out = render(g, view, background=BACKGROUND, capacity=4096) if hand_written else \
            render_arrays(GaussianArrays.from_gaussians(g, g.sh_degree), view, background=BACKGROUND, capacity=4096)
        dr.backward(dr.sum(out.rgb.array), flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        grads.append({k: np.array(dr.grad(getattr(g, k))) for k in NAMES})
    for k in NAMES:
        np.testing.assert_array_equal(grads[0][k], 0.0, err_msg=k)
        np.testing.assert_array_equal(grads[1][k], 0.0, err_msg=k)
