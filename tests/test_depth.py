"""Depth supervision for Mitsuba scenes: the exact depth cached with the references (against a ray-sphere
intersection in closed form), the inverse-depth loss's value and gradient through the rasterizer (finite
differences), frozen training with the depth loss equal to traced training, and the command line."""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
from mi_gaussians.config import OptimConfig, SceneConfig
from mi_gaussians.data.camera import Camera
from mi_gaussians.data.scene_dataset import load_scene_dataset
from mi_gaussians.data.scene_references import reference_depth
from mi_gaussians.optim.losses import depth_loss, inverse_depth_target
from mi_gaussians.raster.rasterize import render
import scene_factory as sf
from test_mitsuba_scene import scene_file, write_scene  # noqa: F401  (scene_file is a fixture)
from test_train_step import one_thread  # noqa: F401  (a fixture)


def test_reference_depth_of_a_sphere_is_exact():
    centre, radius = np.array([0.3, -0.2, 4.0]), 1.1
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "center": centre.tolist(), "radius": radius}})
    w2c = np.eye(4)
    w2c[:3, :3] = [[0.96, 0.0, -0.28], [0.0, 1.0, 0.0], [0.28, 0.0, 0.96]]     # a turned camera
    w2c[:3, 3] = [0.1, 0.05, -0.2]
    cam = Camera(width=48, height=40, fx=40.0, fy=42.0, cx=23.0, cy=21.5, world_to_camera=w2c)
    depth = reference_depth(scene, cam)
    u, v = np.meshgrid(np.arange(48) + 0.5, np.arange(40) + 0.5)
    d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1)
    d = d_cam / np.linalg.norm(d_cam, axis=-1, keepdims=True)
    d_world = d @ w2c[:3, :3]
    oc = cam.center - centre
    b = d_world @ oc
    disc = b * b - (oc @ oc - radius * radius)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0))
    z = t * d[..., 2]
    margin = np.abs(disc) > 0.05 * radius * radius          # (rays that graze the sphere: either answer)
    assert hit[margin].sum() > 300 and (~hit[margin]).sum() > 100
    np.testing.assert_allclose(depth[hit & margin], z[hit & margin], rtol=2e-5)
    assert np.all(np.isinf(depth[~hit & margin]))
    target = inverse_depth_target(depth)
    assert np.all(target[~hit & margin] == 0) and np.allclose(target[hit & margin], 1 / z[hit & margin], rtol=1e-4)


def _depth_loss_numpy(params, cam, inv_target):
    g = mig.Gaussians.from_numpy(**params)
    out = render(g, cam)
    return float(depth_loss(out.depth, out.alpha, mi.TensorXf(inv_target))[0]), out


def test_depth_loss_value_and_gradient():
    params, cam = sf.random_scene(seed=3, n=12, sh_degree=0, width=24, height=20)
    params = {k: np.asarray(v, np.float32) for k, v in params.items()}
    params["opacities"] = np.full_like(params["opacities"], 3.0)        # mostly covered pixels
    _, out = _depth_loss_numpy(params, cam, np.zeros((20, 24), np.float32))
    depth, alpha = np.array(out.depth, np.float64), np.array(out.alpha, np.float64)
    rng = np.random.default_rng(0)
    inv_target = (1 / np.where(depth > 0, depth, 1) * rng.uniform(0.8, 1.2, depth.shape)).astype(np.float32)
    inv_target[rng.random(depth.shape) < 0.2] = 0.0                     # pixels where the scene has no surface
    value, _ = _depth_loss_numpy(params, cam, inv_target)
    valid = (inv_target > 0) & (alpha > 0.5) & (depth > 0)
    assert valid.sum() > 100
    expect = np.sum(np.abs(1 / depth[valid] - inv_target[valid])) / depth.size
    assert value == pytest.approx(expect, rel=1e-5)
    # its gradient w.r.t. the rendered depth: -sign(1/d - r) / d^2 / (H W) on valid pixels, 0 elsewhere
    d_t, a_t = mi.TensorXf(depth.astype(np.float32)), mi.TensorXf(alpha.astype(np.float32))
    dr.enable_grad(d_t)
    dr.backward(depth_loss(d_t, a_t, mi.TensorXf(inv_target)))
    with np.errstate(divide="ignore", invalid="ignore"):
        analytic = np.where(valid, -np.sign(1 / depth - inv_target) / depth ** 2, 0.0) / depth.size
    np.testing.assert_allclose(np.array(dr.grad(d_t), np.float64), analytic, rtol=1e-5, atol=1e-12)
    # through the rasterizer: the chain rule with that image gradient (the rasterizer's depth gradient is checked
    # against float64 finite differences in test_raster.py)
    from raster_helpers import NAMES, gradients_numpy

    chained, _ = gradients_numpy(params, cam, {"rgb": np.zeros((20, 24, 3)), "alpha": np.zeros((20, 24)),
                                               "depth": analytic})
    g = mig.Gaussians.from_numpy(**params)
    for k in NAMES:
        dr.enable_grad(getattr(g, k))
    out = render(g, cam)
    dr.backward(depth_loss(out.depth, out.alpha, mi.TensorXf(inv_target)))
    for k in ("means", "scales", "rotations", "opacities"):
        ours = np.array(dr.grad(getattr(g, k)), np.float64).reshape(chained[k].shape)
        np.testing.assert_allclose(ours, chained[k], rtol=2e-4, atol=1e-9 * np.abs(chained[k]).max(), err_msg=k)
        assert np.abs(ours).max() > 0, k


def test_frozen_training_with_depth_equals_traced(scene_file, tmp_path, one_thread):  # noqa: F811
    from mi_gaussians.config import TrainConfig
    from mi_gaussians.optim.trainer import Trainer

    from test_train_step import _train_ds, assert_same_training

    ds = load_scene_dataset(scene_file, SceneConfig(views=6, test_views=1, init_points=2000, resolution=(24,)),
                            cache_root=tmp_path / "refs", progress=False)
    assert all(v.load_depth() is not None and np.isfinite(v.load_depth()).any() for v in ds.views)
    cfg = TrainConfig(optim=OptimConfig(iterations=60, position_lr_max_steps=60, sh_degree=1, depth_weight=1.0,
                                        depth_weight_final=0.01), checkpoint_every=1000, eval_every=0,
                      save_iterations=())
    frozen = _train_ds(ds, cfg, 60)
    traced = _train_ds(ds, dataclasses.replace(cfg, freeze=False), 60)
    assert frozen.train_step.recordings >= 1
    assert_same_training(frozen, traced)
    from mi_gaussians.evaluate import depth_error

    err = depth_error(frozen.gaussians, ds.test)
    assert err is not None and err["depth_mae"] > 0 and 0 < err["coverage"] <= 1
    # the depth term is in the loss: a run without it differs
    plain = _train_ds(ds, dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, depth_weight=0.0)), 60)
    assert plain.history.loss != frozen.history.loss
    with pytest.raises(ValueError, match="depth supervision"):
        Trainer(dataclasses.replace(ds, train=[dataclasses.replace(v, depth_path=None) for v in ds.train]), cfg,
                tmp_path / "none", progress=False)


def test_cli_depth_weight_needs_a_scene_file(tmp_path):
    from synthetic_dataset import make_blender_dataset

    scene = make_blender_dataset(tmp_path / "scene")
    from test_cli import run

    r = run("optimize", scene, "-o", tmp_path / "o", "--depth-weight", "1")
    assert r.returncode == 2 and "scene .xml" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    for settings, words in ((["--set", "optim.depth_weight=1"], "scene .xml"),
                            (["--set", "data.init=sphere"], "data.init")):
        r = run("optimize", scene, "-o", tmp_path / "o", *settings)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "o").exists()
