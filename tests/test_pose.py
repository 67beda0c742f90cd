"""Camera pose optimisation (``--pose-opt``, mi_gaussians/optim/pose.py) and known pose errors (data/pose_noise.py).

The gradient of a render with respect to a camera's correction is checked against float64 central finite differences
of the independent reference renderer (tests/reference.py), whose cameras this file moves with its own NumPy
transcription of gsplat's ``CameraOptModule`` (``c2w @ [[rot6d(p + identity), dx], [0, 1]]``), so neither the
correction's formula nor the rasterizer is taken on trust. The rest: the owner's sparse Adam step and weight decay,
checkpoints, the COLMAP writer, the noise's exact sizes, and training runs that undo a known pose error.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from types import SimpleNamespace

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
import scene_factory as sf
from raster_helpers import random_weights, weighted_loss
from reference import render_losses
from test_train import load, scene, small_config  # noqa: F401  (scene is a fixture)
from test_raster import each_layout  # noqa: F401  (a fixture: every lane layout of the blend kernels)
from test_train_step import assert_same_training, one_thread, stopped_and_resumed  # noqa: F401  (a fixture)

from mi_gaussians.config import OptimConfig, TrainConfig
from mi_gaussians.data.colmap import matrix_to_quaternion, quaternion_to_matrix
from mi_gaussians.data.pose_noise import perturbed_cameras, pose_errors, reprojection_error
from mi_gaussians.optim.pose import PoseDeltas, adjusted_view
from mi_gaussians.raster.projection import ViewParams

BACKGROUND = (0.3, 0.5, 0.7)
EXTENT = 2.5


def _moved_camera(cam, p, extent=EXTENT, pivot=0.0):
    """The test's own transcription: camera-to-world times [[rot6d(p[3:] + identity), p[:3] * extent], [0, 1]], that
    correction conjugated by the move to the pivot (0, 0, pivot) in camera axes (a turn about it, not the centre)."""
    a1 = np.array(p[3:6]) + [1.0, 0.0, 0.0]
    a2 = np.array(p[6:9]) + [0.0, 1.0, 0.0]
    b1 = a1 / np.linalg.norm(a1)
    b2 = a2 - np.dot(b1, a2) * b1
    b2 = b2 / np.linalg.norm(b2)
    fix = np.eye(4)
    fix[:3, :3] = np.stack([b1, b2, np.cross(b1, b2)])      # rows b1, b2, b3 (pytorch3d's rotation_6d_to_matrix)
    fix[:3, 3] = np.array(p[:3]) * extent
    to_pivot = np.eye(4)
    to_pivot[2, 3] = pivot
    w2c = np.linalg.inv(np.linalg.inv(cam.world_to_camera) @ to_pivot @ fix @ np.linalg.inv(to_pivot))
    return SimpleNamespace(width=cam.width, height=cam.height, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy,
                           world_to_camera=w2c)


def _set(deltas: PoseDeltas, value) -> None:
    """Give ``deltas`` these corrections (its Adam state as it was)."""
    saved = deltas.export()
    saved["value"] = np.asarray(value, np.float32)
    deltas.restore(saved)


def _our_gradient(params, cam, p0, weights, pivot=0.0):
    g = mig.Gaussians.from_numpy(**params)
    p = mi.Float(np.asarray(p0, np.float32))
    dr.enable_grad(p)
    items = [dr.gather(mi.Float, p, k) for k in range(9)]
    view = adjusted_view(ViewParams.from_camera(cam), items, EXTENT, mi.Float(pivot))
    out = mig.render(g, view, background=BACKGROUND)
    dr.backward(weighted_loss(out, weights))
    return np.array(dr.grad(p), np.float64)


def _fd_gradient(params, cam, p0, weights, eps, pivot=0.0):
    cams = []
    for k in range(9):
        for sign in (1.0, -1.0):
            p = np.array(p0, np.float64)
            p[k] += sign * eps
            cams.append(_moved_camera(cam, p, pivot=pivot))
    losses = [render_losses([params], c, weights, background=BACKGROUND)[0][0] for c in cams]
    return np.array([(losses[2 * k] - losses[2 * k + 1]) / (2 * eps) for k in range(9)])


@pytest.mark.parametrize("seed,pivot", [(0, 0.0), (1, 0.0), (2, 3.0)])
def test_view_correction_gradient_matches_finite_differences(seed, pivot):
    """(pivot 3: turning about a point ahead of the camera, optim.pose_opt_pivot = "depth")"""
    params, cam = sf.random_scene(seed=30 + seed, n=12, sh_degree=2, width=24, height=20)
    weights = random_weights(cam, seed=seed)
    rng = np.random.default_rng(seed)
    p0 = rng.normal(scale=0.01, size=9)                     # away from the identity: every term of the formula counts
    ours = _our_gradient(params, cam, p0, weights, pivot)
    fd = _fd_gradient(params, cam, p0, weights, eps=1e-5, pivot=pivot)
    scale = np.abs(fd).max()
    assert scale > 1e-2
    np.testing.assert_allclose(ours, fd, rtol=0, atol=2e-3 * scale)
    # each of the nine numbers matters and is checked on its own (relative error where it is not negligible)
    significant = np.abs(fd) > 0.05 * scale
    assert significant.sum() >= 6
    assert np.all(np.abs(ours - fd)[significant] / np.abs(fd)[significant] < 1e-2)


@pytest.mark.parametrize("pivot", [0.0, 3.0])
def test_view_correction_gradient_matches_drjit_ad_through_the_brute_force_loop(each_layout, pivot):  # noqa: F811
    """The same derivative against a second, independent backward: Dr.Jit's own reverse-mode AD through a per-pixel
    loop over every Gaussian (no tiles, no hand-written blend backward), with every lane layout of the blend kernels
    (the CUDA backend's included), so both backends' code paths are checked here."""
    from drjit_loop_reference import loop_ad_render

    params, cam = sf.random_scene(seed=33, n=15, sh_degree=2, width=24, height=20)
    weights = random_weights(cam, seed=4)
    p0 = np.random.default_rng(4).normal(scale=0.01, size=9)
    ours = _our_gradient(params, cam, p0, weights, pivot)
    p = mi.Float(np.asarray(p0, np.float32))
    dr.enable_grad(p)
    view = adjusted_view(ViewParams.from_camera(cam), [dr.gather(mi.Float, p, k) for k in range(9)], EXTENT,
                         mi.Float(pivot))
    loop_ad_render(params, cam, weights, background=BACKGROUND, view=view)
    theirs = np.array(dr.grad(p), np.float64)
    scale = np.abs(theirs).max()
    assert scale > 1e-2
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-4 * scale)


def test_zero_correction_is_the_view_itself():
    params, cam = sf.random_scene(seed=3, n=20, sh_degree=1, width=32, height=24)
    g = mig.Gaussians.from_numpy(**params)
    plain = np.array(mig.render(g, cam, background=BACKGROUND).rgb)
    view = adjusted_view(ViewParams.from_camera(cam), [mi.Float(0.0)] * 9, EXTENT)
    moved = np.array(mig.render(g, view, background=BACKGROUND).rgb)
    np.testing.assert_allclose(moved, plain, atol=1e-6)


@pytest.mark.parametrize("pivot", [0.0, 3.0])
def test_correction_moves_the_camera_as_the_numpy_transcription(pivot):
    _, cam = sf.random_scene(seed=4, n=2, width=16, height=16)
    p = np.array([0.01, -0.02, 0.005, 0.03, -0.01, 0.02, 0.01, 0.02, -0.04])
    deltas = PoseDeltas(1, OptimConfig(), EXTENT, np.array([pivot]))
    _set(deltas, p[None])
    moved = deltas.cameras([cam])[0]
    np.testing.assert_allclose(moved.world_to_camera,
                               _moved_camera(cam, p.astype(np.float32), pivot=pivot).world_to_camera, atol=1e-6)
    view = deltas.view(ViewParams.from_camera(cam), 0)
    np.testing.assert_allclose(np.array(view.R, np.float64).reshape(3, 3), moved.world_to_camera[:3, :3], atol=1e-6)
    np.testing.assert_allclose(np.array(view.t, np.float64).ravel(), moved.world_to_camera[:3, 3], atol=1e-5)
    np.testing.assert_allclose(np.array(view.center, np.float64).ravel(), moved.center, atol=1e-5)


def test_a_turn_about_the_pivot_keeps_the_pivot_where_it_was():
    """A pure rotation about the pivot (0, 0, z): the point there stays at the same place in the image and at depth z,
    the centre moves on the sphere of radius z about it; about the centre (pivot 0) the centre stays and the point
    moves by f tan(a)."""
    cam = sf.look_at([3.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    a = math.radians(0.5)
    p = np.zeros(9)
    p[3:6] = [math.cos(a), 0.0, -math.sin(a)]     # the 6D form's first row: a turn by a about the camera's y axis
    p[3:6] -= [1.0, 0.0, 0.0]
    target = np.zeros((1, 3))
    about_pivot = PoseDeltas(1, OptimConfig(), EXTENT, np.array([3.0]))
    _set(about_pivot, p[None])
    moved = about_pivot.cameras([cam])[0]
    uv0, z0 = cam.project(target)
    uv1, z1 = moved.project(target)
    np.testing.assert_allclose(uv1, uv0, atol=1e-5)
    np.testing.assert_allclose(z1, z0, atol=1e-6)
    assert np.linalg.norm(moved.center - target[0]) == pytest.approx(3.0, abs=1e-6)
    assert np.linalg.norm(moved.center - cam.center) == pytest.approx(2 * 3.0 * math.sin(a / 2), rel=1e-4)
    assert pose_errors([moved], [cam])[0] == pytest.approx(0.5, rel=1e-4)
    about_centre = PoseDeltas(1, OptimConfig(), EXTENT)
    _set(about_centre, p[None])
    turned = about_centre.cameras([cam])[0]
    np.testing.assert_allclose(turned.center, cam.center, atol=1e-6)
    assert np.linalg.norm(turned.project(target)[0] - uv0) == pytest.approx(cam.fx * math.tan(a), rel=1e-4)


def test_pivot_depths():
    """sum(1/z) / sum(1/z^2) of the points a camera sees; the scene centre's depth without any; 0 when that is behind."""
    from mi_gaussians.optim.pose import pivot_depths

    cam = sf.look_at([3.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    on_axis = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-30.0, 0.0, 0.0], [0.0, 0.0, 50.0], [6.0, 0.0, 0.0]])
    # on the axis at depths 3, 2 and 33: seen; 50 above the target: outside the image; at depth -3: behind
    z = np.array([3.0, 2.0, 33.0])
    assert pivot_depths([cam], on_axis)[0] == pytest.approx(np.sum(1 / z) / np.sum(1 / z ** 2), rel=1e-12)
    assert pivot_depths([cam], np.array([[0.0, 0.0, 0.0]] * 3))[0] == pytest.approx(3.0, rel=1e-12)
    away = sf.look_at([3.0, 0.0, 0.0], [6.0, 0.0, 0.0])              # looking away from the points and the centre
    np.testing.assert_allclose(pivot_depths([cam, away], None, np.zeros(3)), [3.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(pivot_depths([away], on_axis[:2], np.zeros(3)), [0.0], atol=1e-12)
    assert pivot_depths([cam], None)[0] == 0.0


def test_sparse_step_moves_only_the_rendered_camera_and_decays_it():
    params, cam = sf.random_scene(seed=5, n=20, sh_degree=0, width=24, height=20)
    g = mig.Gaussians.from_numpy(**params)
    deltas = PoseDeltas(3, OptimConfig(pose_opt_lr=1e-3, pose_opt_reg=0.5), EXTENT)
    start = np.zeros((3, 9), np.float32)
    start[0, 3] = 0.1                          # camera 0 holds a correction, never rendered here
    _set(deltas, start)
    for _ in range(3):
        out = mig.render(g, deltas.view(ViewParams.from_camera(cam), 1), background=BACKGROUND)
        dr.backward(dr.sum(out.rgb.array))
        deltas.step(1)
    after = deltas.deltas()
    assert np.all(after[0] == start[0]) and np.all(after[2] == 0)       # sparse: the others untouched
    assert np.abs(after[1]).max() > 1e-4
    # the weight decay reaches only the rendered row too: a row with a correction and no gradient keeps it
    deltas.step(0)                             # no backward pass: no gradient; the decay alone moves row 0
    assert deltas.deltas()[0, 3] < 0.1
    assert np.all(deltas.deltas()[2] == 0)


def test_the_rate_decays_over_the_schedule():
    cfg = OptimConfig(pose_opt_lr=1e-3, pose_opt_lr_decay=0.01, position_lr_max_steps=1000)
    deltas = PoseDeltas(2, cfg, EXTENT)
    assert deltas.learning_rate(0) == pytest.approx(1e-3)
    assert deltas.learning_rate(500) == pytest.approx(1e-4)              # the geometric mean, halfway
    assert deltas.learning_rate(1000) == pytest.approx(1e-5) == deltas.learning_rate(5000)
    assert PoseDeltas(2, OptimConfig(pose_opt_lr=2e-4), EXTENT).learning_rate(700) == 2e-4      # (default: constant)
    assert PoseDeltas(2, OptimConfig(pose_opt_lr=0.0, pose_opt_lr_decay=0.1), EXTENT).learning_rate(700) == 0.0


def test_masked_step_changes_nothing():
    params, cam = sf.random_scene(seed=6, n=10, sh_degree=0, width=24, height=20)
    g = mig.Gaussians.from_numpy(**params)
    deltas = PoseDeltas(2, OptimConfig(pose_opt_lr=1e-3), EXTENT)
    out = mig.render(g, deltas.view(ViewParams.from_camera(cam), 1), background=BACKGROUND)
    dr.backward(dr.sum(out.rgb.array))
    before = deltas.export()
    deltas.step(1, active=mi.Bool(False))
    after = deltas.export()
    for k in before:
        np.testing.assert_array_equal(before[k], after[k], err_msg=k)


def test_export_restore_round_trip_and_wrong_shape():
    a = PoseDeltas(4, OptimConfig(), EXTENT)
    value = np.random.default_rng(0).normal(size=(4, 9)).astype(np.float32)
    _set(a, value)
    b = PoseDeltas(4, OptimConfig(), EXTENT)
    b.restore(a.export())
    np.testing.assert_array_equal(b.deltas(), a.deltas())
    with pytest.raises(ValueError, match="4 training cameras"):
        _set(PoseDeltas(4, OptimConfig(), EXTENT), np.zeros((3, 9)))
    # the pivots travel with the corrections (they give them their meaning); a checkpoint from before pivots: centres
    c = PoseDeltas(4, OptimConfig(), EXTENT, np.array([1.0, 2.0, 3.0, 4.0]))
    b.restore(c.export())
    np.testing.assert_array_equal(b.pivots, [1.0, 2.0, 3.0, 4.0])
    old = {k: v for k, v in c.export().items() if k != "pivot"}
    c.restore(old)
    np.testing.assert_array_equal(c.pivots, 0.0)
    with pytest.raises(ValueError, match="pivots"):
        PoseDeltas(2, OptimConfig(), EXTENT, np.array([1.0, -1.0]))


def test_quaternion_round_trip_every_branch():
    rng = np.random.default_rng(1)
    qs = [np.array(q, float) for q in ([1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0.1, 0.9, -0.3, 0.2],
                                        [0.05, -0.2, 0.95, 0.1], [0.02, 0.1, -0.1, 0.99])]
    qs += list(rng.normal(size=(50, 4)))
    for q in qs:
        q = q / np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        back = matrix_to_quaternion(quaternion_to_matrix(q))
        assert back[0] >= 0
        np.testing.assert_allclose(quaternion_to_matrix(back), quaternion_to_matrix(q), atol=1e-12)
        if q[0] > 1e-9:
            np.testing.assert_allclose(back, q, atol=1e-12)


def test_perturbation_has_exactly_the_asked_sizes_and_is_seeded():
    cams = [sf.look_at([3.0 * math.cos(a), 3.0 * math.sin(a), 1.0], [0.0, 0.0, 0.0]) for a in np.linspace(0, 6, 7)]
    moved = perturbed_cameras(cams, 1.0, 0.05, seed=3)
    rot, dist = pose_errors(moved, cams)
    assert rot == pytest.approx(1.0, abs=1e-9) and dist == pytest.approx(0.05, abs=1e-12)
    for m, c in zip(moved, cams):                          # every camera, not only on average
        assert pose_errors([m], [c])[0] == pytest.approx(1.0, abs=1e-9)
        assert np.allclose(m.world_to_camera[:3, :3] @ m.world_to_camera[:3, :3].T, np.eye(3), atol=1e-12)
    again = perturbed_cameras(cams, 1.0, 0.05, seed=3)
    assert all(np.array_equal(a.world_to_camera, b.world_to_camera) for a, b in zip(moved, again))
    other = perturbed_cameras(cams, 1.0, 0.05, seed=4)
    assert not np.array_equal(other[0].world_to_camera, moved[0].world_to_camera)
    rot0, dist0 = pose_errors(perturbed_cameras(cams, 0.0, 0.0, seed=3), cams)
    assert rot0 < 1e-10 and dist0 < 1e-12
    assert pose_errors(perturbed_cameras(cams, 0.01, 0.0, seed=3), cams)[0] == pytest.approx(0.01, rel=1e-6)


def _turned(cam, axis_row: int, angle: float, move=(0.0, 0.0, 0.0)):
    """``cam`` turned by ``angle`` radians about its own axis ``axis_row`` (0 x, 1 y) through its centre, and its
    centre moved by ``move`` (world units)."""
    c, s = math.cos(angle), math.sin(angle)
    turn = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) if axis_row == 1 else \
        np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    R = turn @ cam.world_to_camera[:3, :3]
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, -R @ (cam.center + np.asarray(move))
    return dataclasses.replace(cam, world_to_camera=m)


def test_reprojection_error_is_the_image_shift_and_sees_a_turn_traded_for_a_move():
    """Points on the optical axis at depth 3 (the camera's width 64, focal f): a turn by a about the camera's y axis
    moves them by f tan(a) pixels, a sideways move by d by f d / 3; a move of d and the turn atan(d / 3) that
    compensates it leave the image of those points where it was (0 px) while the angle and the centre are off."""
    cam = sf.look_at([3.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    axis = np.zeros((1, 3))                                          # the target, at depth 3
    f, a, d = cam.fx, math.radians(0.5), 0.02
    assert reprojection_error([cam], [cam], axis) == 0.0
    assert reprojection_error([_turned(cam, 1, a)], [cam], axis) == pytest.approx(f * math.tan(a), rel=1e-9)
    right = cam.world_to_camera[0, :3]                               # the camera's x axis in the world
    assert reprojection_error([_turned(cam, 1, 0.0, d * right)], [cam], axis) == pytest.approx(f * d / 3.0, rel=1e-9)
    traded = _turned(cam, 1, math.atan2(d, 3.0), d * right)
    assert reprojection_error([traded], [cam], axis) < 1e-9
    rot, dist = pose_errors([traded], [cam])
    assert rot == pytest.approx(math.degrees(math.atan2(d, 3.0)), rel=1e-9) and dist == pytest.approx(d)
    # the mean over cameras of the mean over the points each sees; points behind or outside the true image left out
    other = sf.look_at([0.0, 3.0, 0.0], [0.0, 0.0, 0.0])
    behind, outside = [6.0, 0.0, 0.0], [0.0, 0.0, 100.0]
    pts = np.array([[0.0, 0.0, 0.0], behind, outside])
    e = reprojection_error([_turned(cam, 1, a), other], [cam, other], pts)
    assert e == pytest.approx(f * math.tan(a) / 2.0, rel=1e-9)
    # more points than max_points: every k-th (here depths 3, 2, 4, 2.5 on the axis, seen by a sideways move)
    deep = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    moved = _turned(cam, 1, 0.0, d * right)
    assert reprojection_error([moved], [cam], deep, max_points=2) == pytest.approx(f * d * (1 / 3 + 1 / 4) / 2, rel=1e-9)
    assert reprojection_error([moved], [cam], deep) == pytest.approx(f * d * (1 / 3 + 1 / 2 + 1 / 4 + 1 / 2.5) / 4,
                                                                     rel=1e-9)
    assert reprojection_error([cam], [cam], np.zeros((0, 3))) is None and reprojection_error([cam], [cam], None) is None


def test_pose_settings_are_checked():
    cfg = TrainConfig().with_settings(["data.pose_noise=1,0.01", "optim.pose_opt=true"])
    assert cfg.data.pose_noise == (1.0, 0.01) and cfg.optim.pose_opt
    with pytest.raises(ValueError, match="data.pose_noise"):
        TrainConfig().with_settings(["data.pose_noise=1"])
    with pytest.raises(ValueError, match="data.pose_noise"):
        TrainConfig().with_settings(["data.pose_noise=-1,0"])
    with pytest.raises(ValueError, match="optim.pose_opt_lr"):
        TrainConfig().with_settings(["optim.pose_opt_lr=-1e-5"])
    with pytest.raises(ValueError, match="optim.pose_opt_lr_decay"):
        TrainConfig().with_settings(["optim.pose_opt_lr_decay=0"])
    with pytest.raises(ValueError, match="optim.pose_opt_pivot"):
        TrainConfig().with_settings(["optim.pose_opt_pivot=middle"])


# ------------------------------------------------------------------------------------------------ training runs
def _pose_cfg(base, **optim):
    return dataclasses.replace(base, optim=dataclasses.replace(base.optim, pose_opt=True, **optim))


def _noisy_trainer(scene, cfg, out, noise=(1.0, 0.0)):
    """A trainer of ``cfg`` on ``scene`` whose training cameras carry the known error ``noise``, as ``mi-gs optimize
    --set data.pose_noise=...`` builds it."""
    from mi_gaussians.data.pose_noise import perturbed_views
    from mi_gaussians.optim.trainer import Trainer

    ds = load(scene, cfg)
    return Trainer(perturbed_views(ds, noise, cfg.data.seed), cfg, out, progress=False,
                   given_cameras=[v.camera for v in ds.train])


def test_a_zero_rate_trains_bit_for_bit_as_without(scene, tmp_path, one_thread):  # noqa: F811
    """(The frozen step; the traced loop trains what it trains: the next test.)"""
    from mi_gaussians.optim.trainer import Trainer

    base = small_config(120)
    fixed = _pose_cfg(base, pose_opt_lr=0.0, pose_opt_reg=0.0)         # (rate 0: the corrections stay zero)
    runs = []
    for cfg, name in ((base, "plain"), (fixed, "fixed")):
        tr = Trainer(load(scene, cfg), cfg, tmp_path / name, progress=False)
        tr.run()
        runs.append(tr)
    assert_same_training(runs[1], runs[0])
    assert np.all(runs[1].poses.deltas() == 0)


def test_frozen_and_traced_training_agree(scene, tmp_path, one_thread):  # noqa: F811
    """With --pose-opt the frozen step (the view index and the decaying rate inputs, the correction and its pivot
    gathered inside) trains exactly what the traced loop trains, corrections included."""
    cfg = _pose_cfg(small_config(120), pose_opt_lr=3e-4, pose_opt_lr_decay=0.03, pose_opt_pivot="depth")
    frozen = _noisy_trainer(scene, cfg, tmp_path / "frozen")
    frozen.run()
    assert np.all(frozen.poses.pivots > 0)                 # (the scene's points' depths: inputs of the frozen step)
    traced = _noisy_trainer(scene, dataclasses.replace(cfg, freeze=False), tmp_path / "traced")
    traced.run()
    assert frozen.train_step.recordings > 0
    assert_same_training(frozen, traced)
    np.testing.assert_array_equal(frozen.poses.deltas(), traced.poses.deltas())
    assert np.abs(frozen.poses.deltas()).max() > 1e-5                  # (they did move)
    constant = _noisy_trainer(scene, _pose_cfg(small_config(120), pose_opt_lr=3e-4), tmp_path / "constant")
    constant.run()                                                      # (the decaying rate reached the steps)
    assert np.abs(constant.poses.deltas() - frozen.poses.deltas()).max() > 1e-6


def test_checkpoint_and_resume_keep_the_corrections(scene, tmp_path, one_thread):  # noqa: F811
    from mi_gaussians.data.colmap import quaternion_to_matrix

    cfg = _pose_cfg(small_config(100), pose_opt_lr=1e-4)
    resumed, whole = stopped_and_resumed(scene, cfg, tmp_path)
    assert_same_training(resumed, whole)
    np.testing.assert_array_equal(resumed.poses.deltas(), whole.poses.deltas())
    # the refined cameras beside the model: the camera JSON and COLMAP's images.txt, in the training views' order
    refined = whole.poses.cameras([v.camera for v in whole.ds.train])
    saved = json.loads((tmp_path / "whole" / "cameras_refined.json").read_text())["train"]
    assert [c["name"] for c in saved] == [v.name for v in whole.ds.train]
    for c, r in zip(saved, refined):
        np.testing.assert_allclose(np.array(c["world_to_camera"]), r.world_to_camera, atol=1e-12)
    lines = [ln for ln in (tmp_path / "whole" / "images_refined.txt").read_text().splitlines()
             if not ln.startswith("#")]
    assert len(lines) == 2 * len(refined)
    for line, r in zip(lines[::2], refined):
        tok = line.split()
        assert tok[9] == r.name and tok[8] == "1"
        np.testing.assert_allclose(quaternion_to_matrix([float(v) for v in tok[1:5]]), r.world_to_camera[:3, :3],
                                   atol=1e-12)
        np.testing.assert_allclose([float(v) for v in tok[5:8]], r.world_to_camera[:3, 3], atol=1e-12)
    poses = json.loads((tmp_path / "whole" / "metrics.json").read_text())["poses"]
    assert poses["optimized"] and poses["rotation_error_degrees"]["start"] == 0.0


def test_a_known_rotation_error_is_undone(scene, tmp_path, ordered_sums):  # noqa: F811
    """Every training camera turned by 1 degree: with --pose-opt the cameras end nearer the truth and the held-out
    views score higher than the same run without it. (Measured at 600 iterations, rate 1e-4: 0.61 degrees left and
    24.3 dB, against 1.0 degrees and 21.5 dB without, and 26.0 dB with exact cameras.) On one thread (``ordered_sums``):
    on two, the order of the gradients' sums varies from run to run, and so did the margin: +1.4 to +2.7 dB over five
    pairs of runs, against the 1.5 asked; on one thread it is +2.18."""
    cfg = small_config(600)
    plain = _noisy_trainer(scene, cfg, tmp_path / "plain")
    m0 = plain.run()
    fixed = _noisy_trainer(scene, _pose_cfg(cfg, pose_opt_lr=1e-4), tmp_path / "fixed")
    m1 = fixed.run()
    assert m0["poses"]["rotation_error_degrees"] == {"start": 1.0, "end": 1.0} and not m0["poses"]["optimized"]
    assert m1["poses"]["rotation_error_degrees"]["start"] == 1.0
    assert m1["poses"]["rotation_error_degrees"]["end"] < 0.8
    px0, px1 = m1["poses"]["reprojection_error_pixels"]["start"], m1["poses"]["reprojection_error_pixels"]["end"]
    assert m0["poses"]["reprojection_error_pixels"]["end"] == px0 > 0 and px1 < 0.8 * px0, (px0, px1)
    assert m1["mean"]["psnr"] > m0["mean"]["psnr"] + 1.5, (m0["mean"]["psnr"], m1["mean"]["psnr"])


def test_command_line(tmp_path):
    """--pose-opt and data.pose_noise through mi-gs: the report, the refined cameras in the manifest, eval and resume;
    render --dataset and the run's dataset take the refined training cameras, test cameras stay as given."""
    from test_cli import run

    from mi_gaussians.run_folder import RunRecord
    from mi_gaussians.runs import run_dataset

    data = Path(__file__).parent / "data" / "tiny_blender"
    out = tmp_path / "run"
    r = run("optimize", data, "-o", out, "--iterations", 40, "--pose-opt", "--set", "data.pose_noise=0.5,0.01",
            "--random-points", 500, "--quiet", "--eval-every", 0)
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "config.json").read_text())["train"]["optim"]["pose_opt"] is True
    printed = json.loads(r.stdout)
    assert printed["pose_rotation_error_degrees"]["start"] == pytest.approx(0.5, abs=1e-6)
    poses = json.loads((out / "metrics.json").read_text())["poses"]
    assert poses["optimized"] and poses["rotation_error_degrees"]["start"] == pytest.approx(0.5, abs=1e-6)
    assert poses["translation_error_of_extent"]["start"] == pytest.approx(0.01, rel=1e-3)
    assert printed["pose_reprojection_error_pixels"]["start"] == poses["reprojection_error_pixels"]["start"] > 0
    created = json.loads((out / ".mi-gs-manifest.json").read_text())["created"]
    assert "cameras_refined.json" in created and "images_refined.txt" in created
    refined = json.loads((out / "cameras_refined.json").read_text())["train"]
    ds = run_dataset(RunRecord.read(out, ""), out)
    assert len(refined) == len(ds.train)
    for v, c in zip(ds.train, refined):
        assert v.name == c["name"] and np.allclose(v.camera.world_to_camera, c["world_to_camera"])
    given = mig.load_dataset(data)
    for v, g in zip(ds.test, given.test):
        np.testing.assert_array_equal(v.camera.world_to_camera, g.camera.world_to_camera)
    r = run("render", out / "point_cloud.ply", "--dataset", data, "--split", "train", "-o", tmp_path / "renders")
    assert r.returncode == 0 and "use the cameras it refined" in r.stderr, r.stderr
    assert run("eval", out).returncode == 0
    r = run("optimize", data, "-o", out, "--resume", "--iterations", 45, "--quiet")
    assert r.returncode == 0, r.stderr
    (out / "cameras_refined.json").write_text("{")                     # damaged: one line, the given cameras
    r = run("render", out / "point_cloud.ply", "--dataset", data, "--split", "train", "-o", tmp_path / "again")
    assert r.returncode == 0 and "keep the dataset's cameras" in r.stderr, r.stderr
    (line,) = [ln for ln in r.stderr.splitlines() if "cameras_refined.json" in ln]     # one line, naming the file
    assert line.startswith("mi-gs: warning: ") and str(out / "cameras_refined.json") in line


def test_a_run_without_test_views_renders_and_scores_through_its_refined_cameras(tmp_path):
    """A COLMAP run with --test-every 0 (every view a training view): render --dataset (which splits the views its own
    way) still finds the refined cameras, by name in either split; the run scores its training view through its
    refined camera."""
    from test_cli import run

    data = Path(__file__).parent / "data" / "tiny_colmap"
    out = tmp_path / "run"
    r = run("optimize", data, "-o", out, "--iterations", 30, "--pose-opt", "--test-every", 0,
            "--set", "data.pose_noise=0.5,0", "--random-points", 500, "--quiet", "--eval-every", 0)
    assert r.returncode == 0, r.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["split"].startswith("train")
    r = run("render", out / "point_cloud.ply", "--dataset", data, "--split", "all", "-o", tmp_path / "renders")
    assert r.returncode == 0 and "use the cameras it refined" in r.stderr and "warning" not in r.stderr, r.stderr
