"""The alpha loss (``optim.alpha_weight``): on images with alpha, the rendered alpha is held to the image's.

Why it exists: trained over a fixed background, a Gaussian of the background's colour in empty space costs the
photometric loss nothing in the views where it is seen against the background, so a black floater over a black
background stays, and hides the object in the views where it is in front of it (issue 52). Its alpha is what
gives it away.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
import scene_factory as sf
from mi_gaussians.optim.losses import alpha_loss
from mi_gaussians.raster.rasterize import render
from test_train import load, scene, small_config  # noqa: F401  (scene is a fixture)
from test_train_step import _train, _train_ds, assert_same_training, one_thread  # noqa: F401  (one_thread: a fixture)


def test_alpha_loss_is_the_mean_absolute_alpha_difference():
    rng = np.random.default_rng(0)
    alpha, target = rng.uniform(0, 1, (5, 7)).astype(np.float32), rng.uniform(0, 1, (5, 7)).astype(np.float32)
    a = mi.TensorXf(alpha)
    dr.enable_grad(a)
    loss = alpha_loss(a, mi.TensorXf((1.0 - target)[..., None]))
    dr.backward(loss)
    assert float(loss[0]) == pytest.approx(np.mean(np.abs(alpha - target)), rel=1e-5)
    np.testing.assert_allclose(np.array(dr.grad(a)), np.sign(alpha - target) / alpha.size, rtol=1e-6)


def test_a_floater_of_the_background_colour_is_free_but_for_its_alpha():
    """A black Gaussian in front of a black background over an empty image: the photometric loss gives its opacity
    no gradient, the alpha loss pushes it down."""
    cam = sf.generic_camera(32, 32)
    means = sf.pixel_to_world(cam, np.array([16.0]), np.array([16.0]), np.array([3.0]))
    params = sf.make_params(means, np.log(np.full((1, 3), 0.2)), np.array([[1.0, 0, 0, 0]]), sf.logit(np.array([0.8])),
                            np.full((1, 3), -2.0), sh_degree=0)          # SH DC -2: colour max(-2 * C0 + 0.5, 0) = 0
    g = mig.Gaussians.from_numpy(**params)
    dr.enable_grad(g.opacities)
    out = render(g, cam, background=(0.0, 0.0, 0.0))
    empty = mi.TensorXf(np.zeros((32, 32, 3), np.float32))
    from mi_gaussians.optim.losses import photometric_loss

    dr.backward(photometric_loss(out.rgb, empty, 0.2), flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    assert abs(float(dr.grad(g.opacities).array[0])) < 1e-9
    dr.clear_grad(g.opacities)
    out = render(g, cam, background=(0.0, 0.0, 0.0))
    dr.backward(alpha_loss(out.alpha, mi.TensorXf(np.ones((32, 32, 1), np.float32))))
    assert float(dr.grad(g.opacities).array[0]) > 1e-4


def _with_alpha_weight(cfg, weight):
    return dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, alpha_weight=weight))


def test_frozen_training_with_the_alpha_loss_equals_traced_training(scene, one_thread):  # noqa: F811
    cfg = _with_alpha_weight(small_config(300), 0.5)
    frozen = _train(scene, cfg, 110)
    traced = _train(scene, dataclasses.replace(cfg, freeze=False), 110)
    assert frozen.views.transparency is not None
    assert_same_training(frozen, traced)


def test_it_changes_training_only_where_the_images_have_alpha(scene, tmp_path, one_thread):  # noqa: F811
    """On the RGBA scene the alpha loss changes the run; on the same images made opaque (composited, alpha dropped)
    a run with it is the run without it, bit for bit."""
    cfg = small_config(300)
    with_loss, without = (_train(scene, _with_alpha_weight(cfg, w), 40) for w in (0.5, 0.0))
    assert with_loss.history.loss != without.history.loss

    from PIL import Image

    opaque = tmp_path / "opaque"
    for p in scene.rglob("*"):
        dest = opaque / p.relative_to(scene)
        if p.is_dir():
            dest.mkdir(parents=True, exist_ok=True)
        elif p.suffix == ".png":
            dest.parent.mkdir(parents=True, exist_ok=True)
            rgba = np.asarray(Image.open(p).convert("RGBA"), np.float32) / 255.0
            rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])            # over white, as the config's
            Image.fromarray((rgb * 255.0 + 0.5).astype(np.uint8), "RGB").save(dest)
        else:
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_bytes(p.read_bytes())
    a = _train_ds(load(opaque, cfg), _with_alpha_weight(cfg, 0.5), 40)
    b = _train_ds(load(opaque, cfg), cfg, 40)
    assert a.views.transparency is None
    assert_same_training(a, b)
