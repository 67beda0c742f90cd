"""The 'ellipse' footprint (raster/footprint.py): fewer tile instances, the same image and gradients.

Against the 'box' footprint (every tile of the alpha >= alpha_min ellipse's bounding box): the same RGB, alpha, depth
and gradients of every raw parameter, bit for bit (on one thread: gradients are scatter-added, and two threads may
add in another order), on every scene of tests/scene_factory.py (degenerate ones
included) and on a scene of long, thin, turned Gaussians; against independent truth (tests/reference.py's float64
screen-space Gaussians): every tile holding a pixel where a Gaussian's alpha reaches alpha_min has that Gaussian in
its range. And it does save work where a box is loose.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
import scene_factory as sf
from mi_gaussians.config import RasterConfig
from mi_gaussians.raster import blend as blend_module
from mi_gaussians.raster.blend import LaneLayout
from mi_gaussians.raster.rasterize import render
from raster_helpers import NAMES, random_weights, weighted_loss
from reference import preprocess
from test_train_step import one_thread  # noqa: F401  (a fixture: atomic additions in a reproducible order)

BOX, ELLIPSE = RasterConfig(footprint="box"), RasterConfig(footprint="ellipse")


def _count(v) -> int:
    """A render's instance count: a Python int, or a device value of width 1."""
    return int(v[0]) if dr.is_array_v(v) else int(v)


def needles(seed: int = 0, n: int = 300, width: int = 96, height: int = 80):
    """Long thin Gaussians at every angle and opacity, many reaching past the image edge."""
    rng = np.random.default_rng(seed)
    cam = sf.generic_camera(width, height)
    depth = rng.uniform(2.0, 6.0, n)
    px, py = rng.uniform(-0.2, 1.2, n) * width, rng.uniform(-0.2, 1.2, n) * height
    means = sf.pixel_to_world(cam, px, py, depth)
    scales = np.log(np.stack([rng.uniform(0.05, 1.5, n), rng.uniform(0.002, 0.03, n), rng.uniform(0.002, 0.03, n)], 1))
    params = sf.make_params(means, scales, sf.random_quaternions(rng, n), sf.logit(rng.uniform(0.004, 0.999, n)),
                            rng.uniform(0, 1, (n, 3)), sh_degree=1)
    return params, cam


SCENES = {**sf.SCENES, "needles": needles}


def _render(params, cam, cfg, capacity=None, grads=True):
    g = mig.Gaussians.from_numpy(**params)
    if grads:
        for k in NAMES:
            dr.enable_grad(getattr(g, k))
    out = render(g, cam, background=(0.3, 0.5, 0.7), cfg=cfg, capacity=capacity)
    images = {k: np.array(getattr(out, k)) for k in ("rgb", "alpha", "depth")}
    if not grads:
        return images, out
    dr.backward(weighted_loss(out, random_weights(cam, seed=1)), flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    images.update({f"d_{k}": np.array(dr.grad(getattr(g, k))) for k in NAMES})
    images["means2d_grad"] = np.array(out.means2d_grad)
    return images, out


#: A layout whose SIMD packet (16 lanes on the CPU) is one tile: a Gaussian's gradient then gathers its tiles'
#: contributions in the tiles' order whatever else their lists hold. The CPU's default packs two 8 x 8 tiles side
#: by side, whose walks pair up differently when the lists differ (the box's hold more instances), so the two
#: contributions of a Gaussian both tiles hold may be added in the other order (float rounding).
ONE_TILE_PER_PACKET = LaneLayout(pixels=8, start_lanes=16, tile_rows=8, tile_cols=16)


@pytest.mark.parametrize("layout", ["one_tile_per_packet", "default"])
@pytest.mark.parametrize("name", sorted(SCENES))
def test_the_ellipse_renders_and_differentiates_as_the_box(name, layout, one_thread, monkeypatch):  # noqa: F811
    """Bit for bit where a packet is one tile; with the default layout the images bit for bit and the gradients up
    to the order of float sums (2e-4 of the largest: the needles' thin Gaussians cancel large terms, and two layouts
    with the same footprint differ by as much there)."""
    if layout != "default":
        monkeypatch.setattr(blend_module, "lane_layout", lambda: ONE_TILE_PER_PACKET)
    params, cam = SCENES[name](seed=0)
    box, out_box = _render(params, cam, BOX)
    ell, out_ell = _render(params, cam, ELLIPSE)
    for k in box:
        if layout == "default" and (k.startswith("d_") or k == "means2d_grad"):
            scale = max(float(np.nanmax(np.abs(box[k]))), 1e-6) if np.isfinite(box[k]).any() else 1.0
            np.testing.assert_allclose(ell[k], box[k], rtol=0, atol=2e-4 * scale, equal_nan=True, err_msg=k)
        else:
            assert np.array_equal(box[k], ell[k], equal_nan=True), k
    assert out_ell.n_instances == out_box.n_instances           # (the same rectangles are expanded ...)
    assert _count(out_ell.n_blended) <= _count(out_box.n_blended) == out_box.n_instances   # (... fewer blended)


def test_with_a_capacity_too():
    """The frozen training step's path: a fixed instance capacity, its sentinel bucket shared with the dropped
    tiles."""
    params, cam = needles(seed=2)
    exact, out = _render(params, cam, ELLIPSE, grads=False)
    fixed, out_fixed = _render(params, cam, ELLIPSE, capacity=out.n_instances + 77, grads=False)
    assert bool(out_fixed.fits[0])
    for k in exact:
        assert np.array_equal(exact[k], fixed[k]), k
    assert _count(out_fixed.n_blended) == _count(out.n_blended)


@pytest.mark.parametrize("tile", [(16, 16), (16, 8), (8, 8), (16, 4), (4, 8), (16, 1), (1, 4)])
@pytest.mark.parametrize("name", ["needles", "random_deg1", "border_and_outside", "extreme_scales", "opacity_extremes",
                                  "principal_point_off_centre", "odd_size_37x53"])
def test_every_tile_a_gaussian_reaches_holds_it(name, tile):
    """Independent truth: the float64 reference's screen-space Gaussians; every pixel where alpha reaches alpha_min
    (less a rounding allowance) must lie in a tile whose range holds the Gaussian, on grids of tiles of ``tile`` =
    (columns, rows) pixels (the lane layouts')."""
    cols, rows = tile
    from mi_gaussians.raster.binning import bin_gaussians
    from mi_gaussians.raster.projection import GaussianArrays, ViewParams, project

    params, cam = (needles if name == "needles" else sf.SCENES[name])(seed=3)
    g = mig.Gaussians.from_numpy(**params)
    view = ViewParams.from_camera(cam)
    proj = project(GaussianArrays.from_gaussians(g, g.sh_degree), view, ELLIPSE, tile=tile)
    tx, ty = -(-cam.width // cols), -(-cam.height // rows)
    bins = bin_gaussians(proj.depth, proj.rect, proj.tile_count, tx, ty, ellipse=proj.ellipse,
                         image_size=(view.width_f, view.height_f))
    starts, gauss = np.array(bins.tile_start, np.int64), np.array(bins.gaussian, np.int64)
    held = {(int(gauss[i]), t) for t in range(tx * ty) for i in range(starts[t], starts[t + 1])}

    pre = preprocess(params, cam)
    ys, xs = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    tile_of = (ys.astype(int) // rows) * tx + xs.astype(int) // cols
    alpha_min = RasterConfig().alpha_min
    needed = 0
    for i in np.flatnonzero(~pre["culled"]):
        (A, B, C), (mx, my) = pre["conics"][i], pre["means2d"][i]
        dx, dy = xs - mx, ys - my
        alpha = pre["opacities"][i] * np.exp(-0.5 * (A * dx * dx + 2 * B * dx * dy + C * dy * dy))
        for t in np.unique(tile_of[alpha >= alpha_min * (1 + 1e-4)]):
            needed += 1
            assert (int(i), int(t)) in held, (name, i, t)
    assert needed > 0


def test_it_saves_instances_where_a_box_is_loose():
    params, cam = needles(seed=4, n=400)
    _, out = _render(params, cam, ELLIPSE, grads=False)
    assert _count(out.n_blended) < 0.75 * out.n_instances, (_count(out.n_blended), out.n_instances)


def test_the_setting_is_checked():
    from mi_gaussians.config import TrainConfig
    from mi_gaussians.setting_values import SettingError

    with pytest.raises(SettingError, match="raster.footprint"):
        TrainConfig().with_settings(["raster.footprint=circle"]).validate()
    assert dataclasses.replace(RasterConfig(), footprint="box").footprint == "box"
