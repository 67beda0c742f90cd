"""Bilateral grids (``--exposure bilateral``): the slice against a per-pixel float64 reference (tent weights over every
cell, border clamping), the identity grid changing no bit, gradients against finite differences, the total variation
against gsplat's formula, gsplat's learning-rate schedule, the gauge, training bit for bit with a frozen grid,
checkpoints, known per-image gains recovered, the command line and the viewer's files."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
from mi_gaussians.config import OptimConfig
from mi_gaussians.drjit_utils import owned_tensor
from mi_gaussians.metrics import apply_bilateral, fit_affine
from mi_gaussians.optim.adam import masked_step
from mi_gaussians.optim.bilateral import BilateralGrids
from mi_gaussians.optim.schedules import warmup_expon_lr
from test_exposure import gained_dataset
from test_train import load, scene, small_config  # noqa: F401  (scene is a fixture)
from test_train_step import (assert_same_training, one_thread,  # noqa: F401  (one_thread is a fixture)
                             stopped_and_resumed)

SHAPE = (4, 3, 5)           # (x, y, guidance) cells: unequal, so that a swapped axis shows


def with_grids(bg: BilateralGrids, grids: np.ndarray) -> None:
    """Set the (n, L, H, W, 3, 4) grids."""
    t = np.ascontiguousarray(np.asarray(grids, np.float32).transpose(1, 0, 2, 3, 4, 5))
    bg._adam["grids"] = mi.TensorXf(mi.Float(t.ravel()), tuple(bg.tensor.shape))


def noisy_grids(n: int, rng, scale=0.1) -> np.ndarray:
    w, h, levels = SHAPE
    return np.tile(np.eye(3, 4), (n, levels, h, w, 1, 1)) + rng.normal(scale=scale, size=(n, levels, h, w, 3, 4))


def reference_slice(image: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Per pixel, in float64: the transform at (x, y, luma) as the tent-weighted sum over every cell (weight
    max(0, 1 - |coordinate - cell|) per axis), the coordinates clamped to the grid (border padding)."""
    levels, gh, gw = grid.shape[:3]
    h, w = image.shape[:2]
    out = np.zeros((h, w, 3))
    for py in range(h):
        for px in range(w):
            c = image[py, px].astype(np.float64)
            luma = min(max(0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2], 0.0), 1.0)
            at = ((px + 0.5) / w * (gw - 1), (py + 0.5) / h * (gh - 1), luma * (levels - 1))
            e = np.zeros((3, 4))
            for z in range(levels):
                for y in range(gh):
                    for x in range(gw):
                        weight = (max(0.0, 1 - abs(at[0] - x)) * max(0.0, 1 - abs(at[1] - y))
                                  * max(0.0, 1 - abs(at[2] - z)))
                        e += weight * grid[z, y, x]
            out[py, px] = c @ e[:, :3] + e[:, 3]
    return out


def test_slice_matches_a_per_pixel_reference_and_the_identity_is_exact():
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.2, 1.3, (7, 9, 3)).astype(np.float32)      # (luma outside [0, 1] too: border clamping)
    grids = noisy_grids(3, rng)
    bg = BilateralGrids(3, OptimConfig(exposure_grid=SHAPE))
    assert np.array_equal(np.array(bg.apply(owned_tensor(x), 1)), x)      # (the identity, as it starts)
    with_grids(bg, grids)
    want = reference_slice(x, grids[2])
    np.testing.assert_allclose(np.array(bg.apply(owned_tensor(x), 2)), want, atol=2e-6)
    np.testing.assert_allclose(apply_bilateral(x, grids[2]), want, atol=2e-6)
    same = np.tile(grids[0, :1, :1, :1], (1,) + grids.shape[1:4] + (1, 1))    # one transform in every cell:
    np.testing.assert_allclose(apply_bilateral(x, same[0]),                   # the affine transform
                               x @ same[0, 0, 0, 0, :, :3] + same[0, 0, 0, 0, :, 3], atol=2e-6)


def test_gradients_against_finite_differences():
    """d/d(grid) and d/d(rgb) (the guidance's path included) of a weighted sum of the sliced image, against float64
    central differences of the reference."""
    rng = np.random.default_rng(1)
    x = rng.uniform(0.05, 0.95, (4, 5, 3))
    w = rng.normal(size=(4, 5, 3))
    grids = noisy_grids(2, rng, scale=0.2)
    bg = BilateralGrids(2, OptimConfig(exposure_grid=SHAPE))
    with_grids(bg, grids)
    img = owned_tensor(x.astype(np.float32))
    dr.enable_grad(img)
    loss = dr.sum((bg.apply(img, 1) * owned_tensor(w.astype(np.float32))).array)
    dr.backward(loss)
    grad_grid = np.array(dr.grad(bg.tensor)).reshape(SHAPE[2], 2, SHAPE[1], SHAPE[0], 3, 4).transpose(1, 0, 2, 3, 4,
                                                                                                       5)
    grad_x = np.array(dr.grad(img))
    assert np.all(grad_grid[0] == 0)                                # (only the image's own grid)

    def f(g, xx):
        return float(np.sum(reference_slice(xx, g) * w))

    h = 1e-6
    cells = [(0, 0, 0, 0, 0), (2, 1, 3, 1, 3), (4, 2, 1, 2, 2), (1, 1, 2, 0, 1)]
    for cell in cells:
        d = np.zeros_like(grids[1])
        d[cell] = h
        fd = (f(grids[1] + d, x) - f(grids[1] - d, x)) / (2 * h)
        assert abs(grad_grid[1][cell] - fd) < 1e-3 * max(1.0, abs(fd)), (cell, grad_grid[1][cell], fd)
    for idx in [(0, 0, 0), (2, 3, 1), (3, 4, 2), (1, 2, 0)]:
        d = np.zeros_like(x)
        d[idx] = h
        fd = (f(grids[1], x + d) - f(grids[1], x - d)) / (2 * h)
        assert abs(grad_x[idx] - fd) < 1e-3 * max(1.0, abs(fd)), (idx, grad_x[idx], fd)


def test_total_variation_is_gsplats():
    """gsplat's ``total_variation_loss`` of the grids (n, 12, L, H, W): per axis, the sum of squared neighbour
    differences over their count per grid, summed, over the number of grids; times ``optim.exposure_grid_tv``."""
    rng = np.random.default_rng(2)
    grids = noisy_grids(3, rng)
    bg = BilateralGrids(3, OptimConfig(exposure_grid=SHAPE, exposure_grid_tv=7.0))
    with_grids(bg, grids)
    g = grids.reshape(grids.shape[:4] + (12,)).transpose(0, 4, 1, 2, 3)       # (n, 12, L, H, W), gsplat's layout
    want = 0.0
    for axis in (2, 3, 4):
        diff = np.diff(g, axis=axis)
        want += np.sum(diff ** 2) / (diff.size / len(g))
    want /= len(g)
    assert np.isclose(float(bg.regularization()[0]), 7.0 * want, rtol=1e-5)
    assert float(BilateralGrids(3, OptimConfig(exposure_grid=SHAPE)).regularization()[0]) == 0.0


def test_learning_rate_is_gsplats_schedule():
    """``ChainedScheduler([LinearLR(0.01, total_iters=1000), ExponentialLR(0.01 ** (1 / max_steps))])`` after
    k = step - 1 scheduler steps."""
    lr, n = 2e-3, 7000
    for step, factor in ((1, 0.01), (501, (0.01 + 0.99 * 0.5) * 0.01 ** (500 / n)), (1001, 0.01 ** (1000 / n)),
                         (7001, 0.01)):
        assert np.isclose(warmup_expon_lr(step, lr, 1000, 0.01, 0.01, n), lr * factor, rtol=1e-12), step
    bg = BilateralGrids(2, OptimConfig(position_lr_max_steps=n))
    assert np.isclose(bg.learning_rate(1001), lr * 0.01 ** (1000 / n))


def test_a_step_keeps_the_gauge():
    """After a step, the grids' mean over the images and (x, y) is the identity at every guidance level; without the
    gauge, the same step would have moved that mean (here, towards a darker target)."""
    rng = np.random.default_rng(3)
    x = owned_tensor(rng.random((6, 5, 3)).astype(np.float32))
    target = owned_tensor(0.5 * rng.random((6, 5, 3)).astype(np.float32))
    bg = BilateralGrids(3, OptimConfig(exposure_grid=SHAPE))
    bg.set_learning_rate(0.01)
    before = bg.grids()
    dr.backward(dr.sum(dr.square(bg.apply(x, 1) - target).array) + bg.regularization())
    value_before_gauge = None

    def capture(adam, keys, active):                   # (the Adam step alone, as it was before the gauge)
        nonlocal value_before_gauge
        masked_step(adam, keys, active)
        value_before_gauge = np.array(adam["grids"])

    import mi_gaussians.optim.bilateral as module
    original, module.masked_step = module.masked_step, capture
    try:
        bg.step()
    finally:
        module.masked_step = original
    levels = SHAPE[2]
    identity = np.tile(np.eye(3, 4).ravel(), (levels, 1))
    assert np.abs(value_before_gauge.mean(axis=1) - identity).max() > 1e-3        # (Adam alone moved the mean)
    np.testing.assert_allclose(bg.grids().mean(axis=(0, 2, 3)).reshape(levels, 12), identity, atol=1e-6)
    assert np.abs(bg.grids() - before).max() > 1e-3


def test_restore_refuses_another_grid_of_the_same_size():
    """A checkpoint's grids restore into the same layout only: (2 images, 4x4x2 cells) and (2 images, 2x8x2) hold as
    many numbers in the same tensor shape."""
    saved = BilateralGrids(2, OptimConfig(exposure_grid=(4, 4, 2))).export()
    same = BilateralGrids(2, OptimConfig(exposure_grid=(4, 4, 2)))
    same.restore(saved)
    other = BilateralGrids(2, OptimConfig(exposure_grid=(2, 8, 2)))
    assert tuple(other.tensor.shape) == tuple(same.tensor.shape)
    with pytest.raises(ValueError, match="saved bilateral grids of 2 images, 4x4x2 cells; the run has 2 images, 2x8x2"):
        other.restore(saved)


def _bilateral_cfg(cfg, **optim):
    return dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, exposure="bilateral", **optim))


@pytest.mark.parametrize("freeze", [True, False])
def test_a_frozen_identity_grid_trains_bit_for_bit_as_without(scene, tmp_path, one_thread, freeze):  # noqa: F811
    from mi_gaussians.optim.trainer import Trainer

    base = dataclasses.replace(small_config(120), freeze=freeze)
    fixed = _bilateral_cfg(base, exposure_grid_lr=0.0)
    runs = []
    for cfg, name in ((base, "plain"), (fixed, "identity")):
        tr = Trainer(load(scene, cfg), cfg, tmp_path / name, progress=False)
        tr.run()
        runs.append(tr)
    assert_same_training(runs[1], runs[0])
    assert np.array_equal(runs[1].exposure.grids(), np.tile(np.eye(3, 4, dtype=np.float32),
                                                           (runs[1].exposure.n,) + (8, 16, 16) + (1, 1)))


def test_checkpoint_and_resume_keep_the_grids(scene, tmp_path, one_thread):  # noqa: F811
    cfg = _bilateral_cfg(small_config(100), exposure_grid=SHAPE)
    resumed, whole = stopped_and_resumed(scene, cfg, tmp_path)
    assert_same_training(resumed, whole)
    assert np.array_equal(resumed.exposure.grids(), whole.exposure.grids())
    assert not np.allclose(whole.exposure.grids(), np.eye(3, 4), atol=1e-4)          # (they did move)
    with np.load(tmp_path / "whole" / "exposure_grids.npz") as z:
        assert list(z["names"]) == [v.name for v in whole.ds.train]
        assert np.array_equal(z["grids"], whole.exposure.grids())


@pytest.mark.slow
def test_known_per_image_gains_are_recovered(scene, tmp_path):  # noqa: F811
    """Training images scaled by known per-image gains (black background): what each image's grid does to its own
    render, fitted as one affine transform, is that gain times one matrix common to all images, within 7 % (at
    5 times gsplat's learning rate: its rate is made for 30k steps, and moves the grids a half to four fifths of
    the way in the 2,400 here)."""
    from mi_gaussians.optim.trainer import Trainer

    data, gain_of = gained_dataset(scene, tmp_path)
    base = small_config(2400)
    cfg = _bilateral_cfg(dataclasses.replace(base, data=dataclasses.replace(base.data, background=(0.0, 0.0, 0.0))),
                         sh_degree=0, exposure_grid=(4, 4, 8), exposure_grid_lr=0.01)   # (16 pixels a cell)
    tr = Trainer(load(data, cfg), cfg, tmp_path / "run", progress=False)
    tr.run()
    want = np.array([gain_of[v.name] for v in tr.ds.train])
    grids = tr.exposure.grids()
    fitted = []
    for view, grid in zip(tr.ds.train, grids):
        render = np.array(mig.render(tr.params.gaussians, view.camera, background=(0, 0, 0)).rgb)
        lit = render.sum(axis=2) > 0.05                                  # (the object: black stays black anyway)
        fitted.append(fit_affine(render[lit], apply_bilateral(render, grid)[lit]))
    per_gain = np.array(fitted)[:, :, :3] / want[:, None, None]
    common = per_gain.mean(axis=0)
    spread = np.linalg.norm(per_gain - common, axis=(1, 2)) / np.linalg.norm(common)
    print("distance of the fitted E_i / g_i from their mean, relative:", np.round(spread, 3))
    assert np.all(spread < 0.07), spread


def test_command_line_and_viewer_files(tmp_path):
    from test_cli import run

    from mi_gaussians.run_folder import RunRecord
    from mi_gaussians.viewer import render_image
    from mi_gaussians.viewer_entries import run_entries

    data = Path(__file__).parent / "data" / "tiny_blender"
    out = tmp_path / "run"
    r = run("optimize", data, "-o", out, "--iterations", 40, "--exposure", "bilateral", "--random-points", 500,
            "--quiet", "--eval-every", 0, "--set", "optim.exposure_grid=4,3,5")
    assert r.returncode == 0, r.stderr
    cfg = json.loads((out / "config.json").read_text())["train"]
    assert cfg["optim"]["exposure"] == "bilateral" and tuple(cfg["optim"]["exposure_grid"]) == SHAPE
    metrics = json.loads((out / "metrics.json").read_text())
    assert "left half" in metrics["half_image"]["protocol"]
    assert "exposure_grids.npz" in json.loads((out / ".mi-gs-manifest.json").read_text())["created"]
    assert not (out / "exposure.json").exists()
    entries, _, _ = run_entries(RunRecord.read(out, ""), out, warn=pytest.fail)
    train = [e for e in entries if e.exposure is not None]
    grid = train[0].exposure()
    assert grid.shape == (SHAPE[2], SHAPE[1], SHAPE[0], 3, 4) and not np.allclose(grid, np.eye(3, 4), atol=1e-4)
    g = mig.Gaussians.load_ply(out / "point_cloud.ply")                  # an ordinary model; the viewer's frame of
    frame = render_image(g, train[0].camera, exposure=grid)               # the view goes through the view's grid
    raw = np.array(mig.render(g, train[0].camera).rgb)
    want = (np.clip(apply_bilateral(raw, grid), 0, 1) * 255 + 0.5).astype(np.uint8)
    assert np.abs(frame.astype(int) - want.astype(int)).max() <= 1
    # a damaged grids file (emptied, truncated, random bytes, another run's views) is one line, and no exposure
    good = (out / "exposure_grids.npz").read_bytes()
    other = tmp_path / "other.npz"
    np.savez(other, names=np.array(["elsewhere.png"]), grids=np.zeros((1, *grid.shape)))
    for damaged, words in ((b"", "not readable"), (good[: len(good) // 2], "not readable"),
                           (np.random.default_rng(0).bytes(999), "not readable"),
                           (other.read_bytes(), "does not match the run")):
        (out / "exposure_grids.npz").write_bytes(damaged)
        said = []
        entries, _, _ = run_entries(RunRecord.read(out, ""), out, warn=said.append)
        assert len(said) == 1 and said[0].startswith(f"{out / 'exposure_grids.npz'}: {words}"), said
        assert "\n" not in said[0] and all(e.exposure is None for e in entries)
    r = run("optimize", data, "-o", tmp_path / "bad", "--exposure", "bilateral", "--set", "optim.exposure_grid=1,3,5")
    assert r.returncode == 2 and "optim.exposure_grid" in r.stderr, r.stderr
