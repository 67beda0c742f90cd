"""Coarse-to-fine training (optim/resolution.py, optim/targets.py; ``optim.coarse_to_fine=spectrum``).

The schedule: integer scales that never rise, full resolution from ``until`` on, coarser where the images hold less
fine detail, no schedule for an image without any; the same content at twice the size starts no finer. The trainer:
each iteration renders and fits its view at the schedule's scale (targets the area-averages of the images, cameras
the same cameras at that size), frozen steps give the traced loop's model bit for bit, and scores stay at full
resolution.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mi_gaussians.data.images import resize_area
from mi_gaussians.optim.resolution import ResolutionSchedule, scaled_size, spectrum_schedule
from test_train import load, scene, small_config  # noqa: F401  (scene is a fixture)
from test_train_step import _train, assert_same_training, one_thread  # noqa: F401  (one_thread: a fixture)


def _images(kind: str, size: int = 96, n: int = 4, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    out = []
    for _ in range(n):
        if kind == "smooth":
            f = rng.uniform(1, 2, 2)
            im = 0.5 + 0.4 * np.sin(2 * np.pi * (f[0] * x + f[1] * y))
        elif kind == "noise":
            im = rng.uniform(0, 1, (size, size))
        else:
            im = np.full((size, size), 0.3)
        out.append(np.repeat(im[..., None], 3, axis=2).astype(np.float32))
    return out


def test_the_schedule_is_coarse_first_and_full_from_until_on():
    s = spectrum_schedule(_images("smooth"), until=1000)
    scales = [s.scale_at(t) for t in range(1, 1301)]
    assert scales[0] > 1 and all(isinstance(v, int) and v >= 1 for v in scales)
    assert all(a >= b for a, b in zip(scales, scales[1:]))          # (never back to coarser)
    assert set(scales[999:]) == {1}
    assert s.scales_used(1300) == sorted(set(scales), reverse=True)


def test_it_follows_what_the_images_hold():
    smooth, noise = (spectrum_schedule(_images(k), until=1000) for k in ("smooth", "noise"))
    assert smooth.scale_at(1) > noise.scale_at(1)
    flat = spectrum_schedule(_images("flat"), until=1000)
    assert flat.scale_at(1) == 1 and flat.scales_used(1000) == [1]
    assert spectrum_schedule(_images("smooth"), until=0).scale_at(1) == 1


def test_twice_the_image_size_starts_no_finer():
    small = _images("smooth", size=64, seed=3)
    large = [resize_area(np.kron(im, np.ones((2, 2, 1), np.float32)), 128, 128) for im in small]
    a, b = spectrum_schedule(small, 1000), spectrum_schedule(large, 1000)
    assert b.scales[0] >= a.scales[0]


def test_a_schedule_without_levels_is_full_resolution():
    assert ResolutionSchedule((), (), 0).scale_at(5) == 1
    assert scaled_size(200, 150, 3) == (67, 50) and scaled_size(5, 5, 8) == (1, 1)


def _c2f(cfg, until=100):
    return dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, coarse_to_fine="spectrum",
                                                              coarse_until=until))


def test_targets_and_cameras_at_a_scale(scene, tmp_path):  # noqa: F811
    from mi_gaussians.optim.targets import TrainingViews

    cfg = _c2f(small_config(300))
    ds = load(scene, cfg)
    views = TrainingViews(ds, cfg)
    assert views.scale_at(1) > 1, views.schedule
    full = np.array(views.target(2))
    views.set_scale(views.scale_at(1))
    w, h = scaled_size(ds.train[2].camera.width, ds.train[2].camera.height, views.scale)
    np.testing.assert_array_equal(np.array(views.target(2)), resize_area(full, w, h))
    cam = views.camera(2)
    assert (cam.width, cam.height) == (w, h) and cam.fx == pytest.approx(ds.train[2].camera.fx * w / full.shape[1])
    views.set_scale(1)
    np.testing.assert_array_equal(np.array(views.target(2)), full)


def test_frozen_coarse_to_fine_training_equals_traced(scene, one_thread):  # noqa: F811
    """130 iterations whose first 100 climb the scales (several image sizes, each a recording of the frozen step),
    densifying at 100 as well: the frozen loop ends with the traced loop's model, bit for bit."""
    cfg = _c2f(small_config(300))
    frozen = _train(scene, cfg, 130)
    traced = _train(scene, dataclasses.replace(cfg, freeze=False), 130)
    assert len(frozen.views.schedule.scales_used(130)) >= 2
    assert_same_training(frozen, traced)


def test_a_coarse_to_fine_run_scores_at_full_resolution(scene, tmp_path):  # noqa: F811
    from mi_gaussians.optim.trainer import Trainer

    cfg = _c2f(small_config(150), until=120)
    tr = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    before = tr._test_psnr()
    metrics = tr.run()
    assert metrics["mean"]["psnr"] > before + 1.0, (before, metrics["mean"]["psnr"])
    assert (tmp_path / "run" / "renders").is_dir()
    from PIL import Image

    png = next((tmp_path / "run" / "renders").glob("*.png"))
    assert Image.open(png).size == (tr.ds.test[0].camera.width, tr.ds.test[0].camera.height)
