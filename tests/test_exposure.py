"""Per-image exposure compensation (``--exposure affine``): the transform's gradients against finite differences, an
identity transform that trains bit for bit as a run without it, checkpoints that keep the transforms, known per-image
gains recovered, the half-image evaluation protocol, the command line and the viewer's view through a transform."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
from mi_gaussians.drjit_utils import owned_tensor
from mi_gaussians.metrics import apply_affine, fit_affine
from mi_gaussians.optim.exposure import Exposure
from test_train import load, scene, small_config  # noqa: F401  (scene is a fixture)
from test_train_step import assert_same_training, one_thread, stopped_and_resumed  # noqa: F401  (one_thread is a fixture)

E1 = np.array([[1.2, 0.1, 0.0, 0.05], [0.0, 0.9, 0.05, -0.02], [0.02, 0.0, 1.1, 0.01]])


def with_matrix(ex: Exposure, index: int, e: np.ndarray) -> None:
    a = ex.matrices().reshape(ex.n, 12)
    a[index] = np.asarray(e, np.float32).reshape(12)
    ex._adam["exposure"] = mi.TensorXf(mi.Float(a.ravel()), (ex.n, 12))


def test_apply_matches_the_reference_layout_and_identity_is_exact():
    """``c @ E[:, :3] + E[:, 3]`` (the reference's ``rendered.permute(1, 2, 0) @ E[:3, :3] + E[:3, 3]``); the identity
    changes no bit."""
    rng = np.random.default_rng(0)
    x = rng.random((7, 9, 3)).astype(np.float32)
    ex = Exposure(3)
    with_matrix(ex, 2, E1)
    np.testing.assert_allclose(np.array(ex.apply(owned_tensor(x), 2)), x.astype(np.float64) @ E1[:, :3] + E1[:, 3],
                               atol=1e-6)
    assert np.array_equal(np.array(ex.apply(owned_tensor(x), 0)), x)
    assert np.allclose(fit_affine(x, apply_affine(x, E1)), E1, atol=1e-5)


def test_gradients_against_finite_differences():
    """d/dE and d/d(rgb) of a weighted sum of the transformed image, against float64 central differences."""
    rng = np.random.default_rng(1)
    x = rng.random((5, 6, 3))
    w = rng.normal(size=(5, 6, 3))
    ex = Exposure(2)
    with_matrix(ex, 1, E1)
    img = owned_tensor(x.astype(np.float32))
    dr.enable_grad(img)
    loss = dr.sum((ex.apply(img, 1) * owned_tensor(w.astype(np.float32))).array)
    dr.backward(loss)
    grad_e = np.array(dr.grad(ex.tensor)).reshape(2, 3, 4)
    grad_x = np.array(dr.grad(img))

    def f(e, xx):
        return float(np.sum((xx @ e[:, :3] + e[:, 3]) * w))

    h = 1e-6
    fd_e = np.zeros((3, 4))
    for i in range(3):
        for j in range(4):
            d = np.zeros((3, 4))
            d[i, j] = h
            fd_e[i, j] = (f(E1 + d, x) - f(E1 - d, x)) / (2 * h)
    np.testing.assert_allclose(grad_e[1], fd_e, rtol=1e-4, atol=1e-3)
    assert np.all(grad_e[0] == 0)                                   # (only the image's own transform)
    fd_x = np.zeros_like(x)
    for idx in [(0, 0, 0), (2, 3, 1), (4, 5, 2)]:
        d = np.zeros_like(x)
        d[idx] = h
        fd_x[idx] = (f(E1, x + d) - f(E1, x - d)) / (2 * h)
        assert abs(grad_x[idx] - fd_x[idx]) < 1e-4 * max(1.0, abs(fd_x[idx])), idx


def _exposure_cfg(cfg, **optim):
    return dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, exposure="affine", **optim))


def test_a_step_moves_only_the_transform_of_the_view_it_saw():
    """Each step sees one training view, so only that image's transform has a gradient: Adam's moments and momentum
    of the others stay as they were (a sparse step), and the rest of what moves is the gauge's common shift. With a
    dense Adam, image 0's momentum from the first step would keep moving it in the second."""
    rng = np.random.default_rng(2)
    x = owned_tensor(rng.random((4, 5, 3)).astype(np.float32))
    target = owned_tensor(rng.random((4, 5, 3)).astype(np.float32))
    ex = Exposure(3)
    ex.set_learning_rate(0.01)
    before = []
    for index in (0, 1):
        before.append(ex.matrices().reshape(3, 12))
        dr.backward(dr.sum(dr.square(ex.apply(x, index) - target).array))
        ex.step()
    after = ex.matrices().reshape(3, 12)
    moved = after - before[1]                                          # (the second step, which saw image 1)
    np.testing.assert_allclose(moved[0], moved[2], atol=1e-6)          # image 0 moved as image 2, which was never seen:
    assert np.abs(moved[0]).max() > 0                                  # by the gauge's shift alone, -1/3 of image 1's
    np.testing.assert_allclose(moved[1], -2 * moved[0], atol=1e-6)     # own step (which kept the mean: +2/3 of it)
    np.testing.assert_allclose(after.mean(axis=0), np.eye(3, 4).ravel(), atol=1e-6)


@pytest.mark.parametrize("freeze", [True, False])
def test_an_identity_transform_trains_bit_for_bit_as_without(scene, tmp_path, one_thread, freeze):  # noqa: F811
    from mi_gaussians.optim.trainer import Trainer

    base = dataclasses.replace(small_config(120), freeze=freeze)
    fixed = _exposure_cfg(base, exposure_lr_init=0.0, exposure_lr_final=0.0)      # (rate 0: stays the identity)
    runs = []
    for cfg, name in ((base, "plain"), (fixed, "identity")):
        tr = Trainer(load(scene, cfg), cfg, tmp_path / name, progress=False)
        tr.run()
        runs.append(tr)
    assert_same_training(runs[1], runs[0])
    assert np.array_equal(runs[1].exposure.matrices(), np.tile(np.eye(3, 4, dtype=np.float32), (runs[1].exposure.n,
                                                                                                1, 1)))


def test_checkpoint_and_resume_keep_the_transforms(scene, tmp_path, one_thread):  # noqa: F811
    cfg = _exposure_cfg(small_config(100))
    resumed, whole = stopped_and_resumed(scene, cfg, tmp_path)
    assert_same_training(resumed, whole)
    assert np.array_equal(resumed.exposure.matrices(), whole.exposure.matrices())
    assert not np.allclose(whole.exposure.matrices(), np.eye(3, 4))                 # (they did move)
    saved = json.loads((tmp_path / "whole" / "exposure.json").read_text())
    assert list(saved) == [v.name for v in whole.ds.train]
    np.testing.assert_allclose(np.array(list(saved.values())), whole.exposure.matrices(), atol=1e-7)


def gained_dataset(source: Path, tmp_path: Path) -> tuple[Path, dict[str, float]]:
    """A copy of the Blender dataset ``source`` whose training images are scaled by known gains (0.6 to 1.0,
    shuffled), and each training view's gain by its name."""
    import shutil

    from PIL import Image

    data = tmp_path / "gained"
    shutil.copytree(source, data)
    meta = json.loads((data / "transforms_train.json").read_text())
    gains = np.linspace(0.6, 1.0, len(meta["frames"]))
    np.random.default_rng(3).shuffle(gains)
    for gain, frame in zip(gains, meta["frames"]):
        p = data / (frame["file_path"].lstrip("./") + ".png")
        a = np.asarray(Image.open(p)).astype(np.float64)
        a[..., :3] = np.clip(a[..., :3] * gain, 0, 255)             # (straight colour, alpha kept)
        Image.fromarray((a + 0.5).astype(np.uint8)).save(p)
    return data, {f"train/r_{i}.png": float(g) for i, g in enumerate(gains)}


@pytest.mark.slow
def test_known_per_image_gains_are_recovered(scene, tmp_path):  # noqa: F811
    """Training images scaled by known per-image gains (on a black background, none above 1: nothing clips): the
    fitted transforms are those gains times one matrix common to all images (which the model's colours could absorb),
    within 5 %, and that matrix is the one that makes their mean the identity (the gauge the trainer holds: the model
    keeps the images' mean exposure). SH degree 0: view-dependent colour could absorb gains that vary with the
    direction."""
    from mi_gaussians.optim.trainer import Trainer

    data, gain_of = gained_dataset(scene, tmp_path)
    base = small_config(2400)
    cfg = _exposure_cfg(dataclasses.replace(base, data=dataclasses.replace(base.data, background=(0.0, 0.0, 0.0))),
                        sh_degree=0)
    tr = Trainer(load(data, cfg), cfg, tmp_path / "run", progress=False)
    tr.run()
    got = tr.exposure.matrices()
    want = np.array([gain_of[v.name] for v in tr.ds.train])
    # E_i = g_i C for one matrix C common to every image (what the model's colours absorb): the per-image part is
    # the known gain
    per_gain = got[:, :, :3] / want[:, None, None]
    common = per_gain.mean(axis=0)
    spread = np.linalg.norm(per_gain - common, axis=(1, 2)) / np.linalg.norm(common)
    print("distance of E_i / g_i from their mean, relative:", np.round(spread, 3))
    assert np.all(spread < 0.05), spread
    assert np.abs(got[:, :, 3]).max() < 0.05                         # (black stays black: no offsets)
    np.testing.assert_allclose(got.mean(axis=0), np.eye(3, 4), atol=1e-5)
    np.testing.assert_allclose(common, np.eye(3) / want.mean(), atol=0.05 / want.mean())


def test_half_image_protocol_scores_what_a_transform_explains(scene):  # noqa: F811
    """A test image that is the render through some colour transform: the half-image protocol fits it on the left
    half and scores the right half as perfect; the plain score sees the difference."""
    from mi_gaussians.evaluate import evaluate_views
    from mi_gaussians.model.ply import read_ply

    g = mig.Gaussians.load_ply(Path(__file__).resolve().parents[1] / "scenes" / "tiny_gaussians.ply")
    ds = mig.load_dataset(scene, background=(1.0, 1.0, 1.0))
    view = ds.test[0]
    img = np.array(mig.render(g, view.camera, background=(1, 1, 1)).rgb)
    target = apply_affine(img, 0.8 * E1)
    full, _ = evaluate_views(g, [view], (1, 1, 1), with_lpips=False, targets={view.name: target})
    half, _ = evaluate_views(g, [view], (1, 1, 1), with_lpips=False, targets={view.name: target}, protocol="half")
    assert half[0].psnr > 60 and full[0].psnr < 25, (full[0].psnr, half[0].psnr)
    assert read_ply  # (the model is a PLY: nothing of the transform is in it)


def test_command_line(tmp_path):
    from test_cli import run

    data = Path(__file__).parent / "data" / "tiny_blender"
    out = tmp_path / "run"
    r = run("optimize", data, "-o", out, "--iterations", 40, "--exposure", "--random-points", 500, "--quiet",
            "--eval-every", 0)
    assert r.returncode == 0, r.stderr
    cfg = json.loads((out / "config.json").read_text())["train"]
    assert cfg["optim"]["exposure"] == "affine"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["protocol"].startswith("the whole image") and "left half" in metrics["half_image"]["protocol"]
    assert set(metrics["half_image"]["views"]) == set(metrics["views"])
    assert "exposure.json" in json.loads((out / ".mi-gs-manifest.json").read_text())["created"]
    ply = mig.Gaussians.load_ply(out / "point_cloud.ply")                  # an ordinary model
    assert ply.n > 0
    e = run("eval", out)
    assert e.returncode == 0, e.stderr
    evaluated = json.loads((out / "eval.json").read_text())
    assert "half_image" in evaluated and evaluated["protocol"] == metrics["protocol"]
    r = run("optimize", data, "-o", out, "--resume", "--iterations", 45, "--quiet")
    assert r.returncode == 0, r.stderr
    r = run("optimize", data, "-o", tmp_path / "x", "--exposure", "grid")
    assert r.returncode == 2 and "invalid choice" in r.stderr


def test_viewer_shows_a_training_view_through_its_transform(tmp_path):
    """The panel's "Exposure of the chosen view": the frame of a training view goes through that view's transform
    (what the training compared), and back without it."""
    import socket

    from mi_gaussians.viewer import StaticModel, Viewer, ViewerConfig
    from mi_gaussians.viewer_entries import dataset_entries

    root = Path(__file__).resolve().parents[1]
    g = mig.Gaussians.load_ply(root / "scenes" / "tiny_gaussians.ply")
    ds = mig.load_dataset(Path(__file__).parent / "data" / "tiny_blender")
    transforms = {v.name: E1 for v in ds.train}
    entries = dataset_entries(ds, lambda: transforms)
    assert [e.exposure is not None for e in entries] == [True] * len(ds.train) + [False] * len(ds.test)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = Viewer(StaticModel(g), entries, ViewerConfig(port=port))
    viewer.start()
    try:
        cam = entries[0].camera
        plain = viewer.render_frame(g, cam)
        viewer._chosen, viewer._exposure.value = entries[0], True
        through = viewer.render_frame(g, cam)
        raw = np.array(mig.render(g, cam).rgb)
        want = (np.clip(apply_affine(raw, E1), 0, 1) * 255 + 0.5).astype(np.uint8)
        assert np.abs(through.astype(int) - want.astype(int)).max() <= 1
        assert np.abs(through.astype(int) - plain.astype(int)).max() > 5
        viewer._exposure.value = False
        assert np.array_equal(viewer.render_frame(g, cam), plain)
    finally:
        viewer.stop()
