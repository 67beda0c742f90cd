"""The tile-sorted rasterizer against the independent per-pixel reference (tests/reference.py).

Forward: every scene of tests/scene_factory.py (random and adversarial) agrees to 1e-5. Backward: gradients of every
raw parameter against float64 central finite differences of the reference, and against Dr.Jit's own AD through a
brute-force loop. Also: no NaN/Inf anywhere, tile-grid independence, and no recompilation per view.
"""

from __future__ import annotations

import drjit as dr
import numpy as np
import pytest

import mi_gaussians as mig
import scene_factory as sf
from kernel_log import KernelLog
from raster_helpers import NAMES, gradients_numpy, random_weights, render_numpy, weighted_loss
from reference import fd_gradients, render_reference

BACKGROUND = (0.3, 0.5, 0.7)


def _compare(ours, ref, tol=1e-5):
    assert np.all(np.isfinite(ours["rgb"])) and np.all(np.isfinite(ours["alpha"])) and np.all(np.isfinite(ours["depth"]))
    np.testing.assert_allclose(ours["rgb"], ref["rgb"], rtol=0, atol=tol)
    np.testing.assert_allclose(ours["alpha"], ref["alpha"], rtol=0, atol=tol)
    # depth is in world units: compare relative to the depth scale of the scene
    scale = max(1.0, float(np.abs(ref["depth"]).max()))
    np.testing.assert_allclose(ours["depth"], ref["depth"], rtol=0, atol=tol * scale)


# Scenes built to sit exactly on a float32/float64 decision boundary (see their docstrings): there the reference
# takes its discrete decisions in float32 too, like any float32 rasterizer (the reference CUDA code included).
FLOAT32_DECISIONS = {"opaque_stack"}


@pytest.mark.parametrize("name", sorted(sf.SCENES))
def test_forward_matches_reference(name):
    params, cam = sf.SCENES[name](seed=0)
    ours = render_numpy(params, cam, background=BACKGROUND)
    dtype = np.float32 if name in FLOAT32_DECISIONS else np.float64
    ref = render_reference(params, cam, background=BACKGROUND, dtype=dtype)
    _compare(ours, ref)


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("degree", [0, 3])
def test_forward_random_seeds_and_active_degree(seed, degree):
    params, cam = sf.random_scene(seed, n=80, sh_degree=3, width=53, height=37)
    ours = render_numpy(params, cam, background=BACKGROUND, sh_degree=degree)
    ref = render_reference(params, cam, background=BACKGROUND, sh_degree=degree)
    _compare(ours, ref)


@pytest.mark.parametrize("name", sorted(sf.SCENES))
def test_gradients_are_finite(name):
    params, cam = sf.SCENES[name](seed=0)
    if params["means"].shape[0] == 0:
        out = render_numpy(params, cam)
        assert np.all(out["alpha"] == 0)
        return
    grads, _ = gradients_numpy(params, cam, random_weights(cam), background=BACKGROUND)
    for k in NAMES:
        assert np.all(np.isfinite(grads[k])), f"non-finite gradient of {k} in scene {name}"


def _check_fd(params, cam, subset, weights, sh_degree=None, eps=1e-5, rtol=1e-3, antialiased=False):
    ours, _ = gradients_numpy(params, cam, weights, background=BACKGROUND, sh_degree=sh_degree,
                              antialiased=antialiased)
    fd, unreliable = fd_gradients(params, cam, weights, background=BACKGROUND, sh_degree=sh_degree, eps=eps,
                                  index_subset=subset, return_unreliable=True, antialiased=antialiased)
    checked = 0
    for k in NAMES:
        sel = np.zeros(params[k].shape, bool)
        sel[subset] = True
        sel &= ~unreliable[k]
        if not sel.any():
            continue
        a, b = ours[k][sel], fd[k][sel]
        scale = max(np.abs(b).max(), 1e-3)
        significant = np.abs(b) > 1e-2 * scale          # "non-negligible entries"
        rel = np.abs(a - b) / np.maximum(np.abs(b), 1e-12)
        assert np.all(rel[significant] < rtol), (k, rel[significant].max())
        # negligible entries must stay negligible in absolute terms too
        assert np.all(np.abs(a - b)[~significant] < rtol * scale), (k, np.abs(a - b)[~significant].max())
        checked += significant.sum()
    return checked


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_gradients_match_finite_differences(degree):
    params, cam = sf.random_scene(seed=10 + degree, n=10, sh_degree=degree, width=24, height=20)
    checked = _check_fd(params, cam, np.arange(10), random_weights(cam, seed=degree))
    assert checked > 100


@pytest.mark.parametrize("name", ["principal_point_off_centre", "opaque_stack", "single", "border_and_outside"])
def test_gradients_match_finite_differences_special(name):
    params, cam = sf.SCENES[name](seed=0)
    n = params["means"].shape[0]
    subset = np.arange(min(n, 6))
    assert _check_fd(params, cam, subset, random_weights(cam, seed=5)) > 10


def test_a_loss_of_the_alpha_alone_has_the_reference_gradients():
    """With no colour or depth gradient reaching the blend (a mask loss alone: the backward's incoming colour
    gradients are literal zeros), the gradients still match float64 finite differences of the reference."""
    params, cam = sf.random_scene(seed=21, n=10, sh_degree=0, width=24, height=20)
    w = random_weights(cam, seed=3)
    weights = {"rgb": np.zeros_like(w["rgb"]), "alpha": w["alpha"], "depth": np.zeros_like(w["depth"])}
    g = mig.Gaussians.from_numpy(**params)
    for k in NAMES:
        dr.enable_grad(getattr(g, k))
    out = mig.render(g, cam, background=BACKGROUND)
    import mitsuba as mi

    dr.backward(dr.sum(out.alpha.array * mi.Float(weights["alpha"].astype(np.float32).ravel())))
    ours = {k: np.array(dr.grad(getattr(g, k)), dtype=np.float64).reshape(params[k].shape) for k in NAMES
            if params[k].size}
    fd, unreliable = fd_gradients(params, cam, weights, background=BACKGROUND, eps=1e-5, return_unreliable=True)
    checked = 0
    for k in ("means", "scales", "rotations", "opacities"):
        sel = ~unreliable[k]
        a, b = ours[k][sel], fd[k][sel]
        scale = max(np.abs(b).max(), 1e-3)
        significant = np.abs(b) > 1e-2 * scale
        assert np.all(np.abs(a - b)[significant] < 1e-3 * np.abs(b)[significant]), k
        assert np.all(np.abs(a - b)[~significant] < 1e-3 * scale), k
        checked += significant.sum()
    assert checked > 30
    assert np.all(ours["sh_dc"] == 0)                    # (the colour does not change the alpha)


# ------------------------------------------------------------------------------------------------ anti-aliased mode
@pytest.mark.parametrize("name", sorted(sf.SCENES))
def test_antialiased_forward_matches_reference(name):
    params, cam = sf.SCENES[name](seed=0)
    ours = render_numpy(params, cam, background=BACKGROUND, antialiased=True)
    dtype = np.float32 if name in FLOAT32_DECISIONS else np.float64
    ref = render_reference(params, cam, background=BACKGROUND, dtype=dtype, antialiased=True)
    _compare(ours, ref)


@pytest.mark.parametrize("degree", [0, 3])
def test_antialiased_gradients_match_finite_differences(degree):
    params, cam = sf.random_scene(seed=30 + degree, n=10, sh_degree=degree, width=24, height=20)
    params["scales"] = params["scales"] - 1.5      # footprints near a pixel, where the compensation matters
    checked = _check_fd(params, cam, np.arange(10), random_weights(cam, seed=degree), antialiased=True)
    assert checked > 50


@pytest.mark.parametrize("name", sorted(set(sf.SCENES) - {"empty"}))
def test_antialiased_gradients_are_finite(name):
    params, cam = sf.SCENES[name](seed=0)
    grads, _ = gradients_numpy(params, cam, random_weights(cam), background=BACKGROUND, antialiased=True)
    for k in NAMES:
        assert np.all(np.isfinite(grads[k])), f"non-finite gradient of {k} in scene {name}"


@pytest.mark.parametrize("name", ["opaque_stack", "single", "border_and_outside", "degenerate_rotations"])
def test_antialiased_gradients_special_scenes(name):
    params, cam = sf.SCENES[name](seed=0)
    n = params["means"].shape[0]
    assert _check_fd(params, cam, np.arange(min(n, 6)), random_weights(cam, seed=5), antialiased=True) > 10


def test_antialiased_keeps_a_sub_pixel_gaussians_energy():
    """The point of the filter: a Gaussian far smaller than a pixel covers (opacity x its own footprint) worth of
    alpha, not a 0.3-pixel blob at full opacity; a large one is left almost unchanged."""
    from reference import preprocess

    params, cam = sf.random_scene(seed=3, n=2, sh_degree=0, width=32, height=32)
    params["scales"][0] = np.log(1e-4)          # sub-pixel
    params["scales"][1] = 0.0                   # large
    plain = preprocess(params, cam)["opacities"]
    aa = preprocess(params, cam, antialiased=True)["opacities"]
    assert aa[0] < 1e-2 * plain[0] and 0.95 * plain[1] < aa[1] <= plain[1]
    ours = render_numpy(params, cam, antialiased=True)
    ref = render_reference(params, cam, antialiased=True)
    _compare(ours, ref)


def test_means2d_absgrad_is_the_sum_of_per_pixel_absolute_gradients():
    """AbsGS's statistic against its definition: the loss split into one loss per pixel, each pixel's
    dL_pixel/d(mean2d) from the (tested) ordinary backward pass, absolute values summed per axis."""
    params, cam = sf.random_scene(seed=8, n=12, sh_degree=1, width=16, height=12)
    weights = random_weights(cam, seed=2)
    g = mig.Gaussians.from_numpy(**params)
    dr.enable_grad(g.means)
    out = mig.render(g, cam, background=BACKGROUND)
    out.request_absgrad()
    dr.backward(weighted_loss(out, weights))
    absgrad = np.stack([np.array(out.means2d_absgrad.x), np.array(out.means2d_absgrad.y)], axis=1)
    plain = np.stack([np.array(out.means2d_grad.x), np.array(out.means2d_grad.y)], axis=1)
    want = np.zeros_like(absgrad, dtype=np.float64)
    for y in range(cam.height):
        for x in range(cam.width):
            one = {k: np.zeros_like(w) for k, w in weights.items()}
            for k in one:
                one[k][y, x] = weights[k][y, x]
            _, o = gradients_numpy(params, cam, one, background=BACKGROUND)
            want += np.abs(np.stack([np.array(o.means2d_grad.x), np.array(o.means2d_grad.y)], axis=1))
    np.testing.assert_allclose(absgrad, want, rtol=1e-4, atol=1e-6 * np.abs(want).max())
    assert np.all(absgrad >= np.abs(plain) - 1e-5) and np.any(absgrad > np.abs(plain) * 1.5 + 1e-3)
    with pytest.raises(ValueError, match="request_absgrad"):
        mig.render(g, cam).means2d_absgrad


def _assert_matches_loop_ad(params, cam, weights, **kw):
    """The image and the gradients of every parameter against Dr.Jit's reverse-mode AD through a brute-force
    per-pixel loop (``kw``: ``cfg``, the rasterizer's thresholds, for both)."""
    from drjit_loop_reference import loop_ad_render

    ours, out = gradients_numpy(params, cam, weights, background=BACKGROUND, **kw)
    theirs, img = loop_ad_render(params, cam, weights, background=BACKGROUND, **kw)
    np.testing.assert_allclose(np.array(out.rgb).reshape(img["rgb"].shape), img["rgb"], atol=1e-5)
    for k in NAMES:
        scale = max(np.abs(theirs[k]).max(), 1e-6)
        np.testing.assert_allclose(ours[k], theirs[k], rtol=0, atol=1e-4 * scale, err_msg=k)


def test_gradients_match_drjit_loop_ad():
    """Our hand-written backward vs Dr.Jit's reverse-mode AD through a brute-force per-pixel loop."""
    params, cam = sf.random_scene(seed=21, n=30, sh_degree=2, width=40, height=30)
    _assert_matches_loop_ad(params, cam, random_weights(cam, seed=3))


def test_means2d_gradient_exposed():
    """``out.means2d_grad`` is dL/d(projected mean): finite differences of the reference compositing step with
    the 2D means moved and everything else (conics, colours, depths) held fixed."""
    from reference import composite, preprocess
    from reference import weighted_loss as ref_loss

    params, cam = sf.random_scene(seed=4, n=8, sh_degree=2, width=32, height=24)
    weights = random_weights(cam, seed=1)
    _, out = gradients_numpy(params, cam, weights, background=BACKGROUND)
    g2d = np.stack([np.array(out.means2d_grad.x), np.array(out.means2d_grad.y)], axis=1)
    pre = preprocess(params, cam)
    eps = 1e-4
    checked = 0
    for i in range(params["means"].shape[0]):
        for axis in range(2):
            p_plus = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in pre.items()}
            p_minus = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in pre.items()}
            p_plus["means2d"][i, axis] += eps
            p_minus["means2d"][i, axis] -= eps
            fd = (ref_loss(composite(p_plus, cam, BACKGROUND), weights)
                  - ref_loss(composite(p_minus, cam, BACKGROUND), weights)) / (2 * eps)
            assert abs(g2d[i, axis] - fd) <= 1e-3 * max(1e-2, abs(fd)), (i, axis, g2d[i, axis], fd)
            checked += abs(fd) > 1e-3
    assert checked >= 8


def test_radii_follow_the_reference_definition():
    params, cam = sf.random_scene(seed=7, n=40, sh_degree=0)
    ours = render_numpy(params, cam)
    ref = render_reference(params, cam)
    cov = ref["cov2d"]
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    mid = 0.5 * (a + c)
    lam = mid + np.sqrt(np.maximum(0.1, mid * mid - (a * c - b * b)))
    expect = np.where(ref["culled"], 0, np.ceil(3 * np.sqrt(lam)))
    on_screen = ours["radii"] > 0
    assert on_screen.sum() > 20
    np.testing.assert_array_equal(ours["radii"][on_screen], expect[on_screen])


def test_image_independent_of_tile_alignment():
    """Shifting the image window by 5 pixels moves the 16x16 tile grid over the content; pixels must not change.
    (The reference's 3-sigma box fails this for opacities near 1, where alpha stays >= 1/255 beyond 3 sigma.)"""
    params, cam = sf.opacity_extremes(seed=0)
    base = render_numpy(params, cam, background=BACKGROUND)
    shifted_cam = mig.Camera(cam.width + 5, cam.height + 3, cam.fx, cam.fy, cam.cx + 5, cam.cy + 3,
                             cam.world_to_camera)
    shifted = render_numpy(params, shifted_cam, background=BACKGROUND)
    np.testing.assert_allclose(shifted["rgb"][3:, 5:], base["rgb"], rtol=0, atol=2e-6)
    np.testing.assert_allclose(shifted["alpha"][3:, 5:], base["alpha"], rtol=0, atol=2e-6)


def test_no_recompilation_per_view_and_background():
    """Other cameras (of the same size) and other backgrounds launch the kernels of the first views: per-view values
    travel as opaque arrays, never as kernel literals."""
    params, cam = sf.random_scene(seed=3, n=200, sh_degree=3, width=64, height=48)
    g = mig.Gaussians.from_numpy(**params)
    for k in NAMES:
        dr.enable_grad(getattr(g, k))
    from mi_gaussians.raster.rasterize import render

    def one(camera, background, grad=True):
        out = render(g, camera, background=background)
        if not grad:
            dr.eval(out.rgb, out.alpha, out.depth)
            return
        dr.backward(dr.sum(out.rgb.array) + dr.sum(out.depth.array))
        dr.eval([dr.grad(getattr(g, k)) for k in NAMES])

    cams = [sf.generic_camera(64, 48, variant=v % 3) for v in range(10)]
    cams = [mig.Camera(c.width, c.height, c.fx * (1 + 0.01 * i), c.fy, c.cx + i, c.cy - i, c.world_to_camera)
            for i, c in enumerate(cams)]
    backgrounds = [(0.1 * i, 1.0 - 0.05 * i, 0.5) for i in range(10)]     # (a random background per iteration)
    with KernelLog() as log:
        for grad in (True, False):
            one(cams[0], backgrounds[0], grad)
            one(cams[1], backgrounds[1], grad)
        log.cut()
        for c, bg in zip(cams, backgrounds):
            one(c, bg)
            one(c, bg, grad=False)
        log.cut()
    assert len(log.windows[1]) > 10
    unseen = log.unseen(1)
    assert not unseen, f"{len(unseen)} kernels not launched for the first two views: {unseen[:5]}"


def test_render_api_shapes_and_errors():
    params, cam = sf.random_scene(seed=1, n=5, sh_degree=1, width=30, height=20)
    g = mig.Gaussians.from_numpy(**params)
    out = mig.render(g, cam, background=(1, 1, 1))
    assert out.rgb.shape == (20, 30, 3) and out.alpha.shape == (20, 30) and out.depth.shape == (20, 30)
    assert dr.width(out.radii) == 5
    with pytest.raises(ValueError, match="sh_degree"):
        mig.render(g, cam, sh_degree=2)
    with pytest.raises(ValueError, match="background"):
        mig.render(g, cam, background=(1, 1))


# ------------------------------------------------------------------------------------------------ lane layouts
# Each backend maps pixels to lanes its own way (raster/blend.py, LANE_LAYOUTS). Every layout runs here on the CPU,
# the CUDA one included, against the same references.
from mi_gaussians.raster import blend as blend_module  # noqa: E402
from mi_gaussians.raster.blend import LANE_LAYOUTS, LaneLayout  # noqa: E402

LAYOUTS = {**LANE_LAYOUTS, "one_pixel": LaneLayout(pixels=1, start_lanes=256),
           "two_pixels": LaneLayout(pixels=2, start_lanes=8), "column": LaneLayout(pixels=16, start_lanes=1),
           "square_tiles": LaneLayout(pixels=8, start_lanes=16, tile_rows=16),
           "eight_rows": LaneLayout(pixels=8, start_lanes=16, tile_rows=8),
           "four_rows": LaneLayout(pixels=4, start_lanes=16, tile_rows=4),
           "one_row": LaneLayout(pixels=1, start_lanes=4, tile_rows=1),
           "eight_by_eight_four_pixels": LaneLayout(pixels=4, start_lanes=16, tile_rows=8, tile_cols=8),
           "four_columns": LaneLayout(pixels=8, start_lanes=4, tile_rows=8, tile_cols=4),
           "one_column": LaneLayout(pixels=2, start_lanes=2, tile_rows=4, tile_cols=1),
           "image_order": LaneLayout(pixels=8, start_lanes=8, tile_rows=8, tile_cols=8),
           "by_work_sixteen": LaneLayout(pixels=4, start_lanes=16, tile_rows=16, by_work=True),
           "small_tiles": blend_module.SMALL_TILES}


@pytest.fixture(params=sorted(LAYOUTS))
def each_layout(request, monkeypatch):
    monkeypatch.setattr(blend_module, "lane_layout", lambda: LAYOUTS[request.param])
    assert blend_module.make_frame(16, 16, 1).layout is LAYOUTS[request.param]     # (what render's frames get)
    return request.param


@pytest.mark.parametrize("name", ["border_and_outside", "principal_point_off_centre", "opaque_stack", "random"])
def test_every_lane_layout_matches_the_reference(each_layout, name):
    make = sf.SCENES.get(name) or (lambda seed: sf.random_scene(seed, n=40, sh_degree=2, width=53, height=37))
    params, cam = make(seed=0)
    dtype = np.float32 if name in FLOAT32_DECISIONS else np.float64
    _compare(render_numpy(params, cam, background=BACKGROUND),
             render_reference(params, cam, background=BACKGROUND, dtype=dtype))


def test_every_lane_layouts_gradients_match_finite_differences(each_layout):
    params, cam = sf.random_scene(seed=12, n=10, sh_degree=1, width=37, height=21)
    assert _check_fd(params, cam, np.arange(10), random_weights(cam, seed=1)) > 100


def test_lane_layouts_agree_with_each_other():
    """Images bit for bit, gradients up to the order of float sums, between every pair of layouts (a 53 x 37 image:
    partial tiles on both axes; 300 Gaussians: lanes of a group with different last contributors)."""
    params, cam = sf.random_scene(seed=31, n=300, sh_degree=3, width=53, height=37)
    weights = random_weights(cam, seed=2)
    results = {}
    for name, layout in LAYOUTS.items():
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(blend_module, "lane_layout", lambda layout=layout: layout)
            grads, out = gradients_numpy(params, cam, weights, background=BACKGROUND)
            results[name] = (np.array(out.rgb), np.array(out.alpha), np.array(out.depth), grads)
    base_rgb, base_alpha, base_depth, base_grads = results["llvm"]
    for name, (rgb, alpha, depth, grads) in results.items():
        np.testing.assert_array_equal(rgb, base_rgb, err_msg=name)
        np.testing.assert_array_equal(alpha, base_alpha, err_msg=name)
        np.testing.assert_array_equal(depth, base_depth, err_msg=name)
        for k in NAMES:
            scale = max(np.abs(base_grads[k]).max(), 1e-6)
            np.testing.assert_allclose(grads[k], base_grads[k], rtol=0, atol=1e-5 * scale, err_msg=f"{name} {k}")


@pytest.mark.parametrize("layout", ["llvm", "small_tiles", "by_work_sixteen", "cuda"])
@pytest.mark.parametrize("name", ["random", "opaque_stack", "border_and_outside", "empty"])
def test_a_render_without_depth_is_the_same_render_and_gradients(layout, name, monkeypatch):
    """``render(..., depth=False)`` (a training step without a depth loss): ``out.depth`` is None, and the images and
    every gradient of a loss of the colour and the coverage are those of the render with depth, bit for bit; the
    forward's loop then carries no depth sum (its kernel is another, smaller one)."""
    import mitsuba as mi

    monkeypatch.setattr(blend_module, "lane_layout", lambda: LAYOUTS[layout])
    make = sf.SCENES.get(name) or (lambda seed: sf.random_scene(seed, n=120, sh_degree=2, width=53, height=37))
    params, cam = make(seed=3)
    weights = random_weights(cam, seed=4)
    got = {}
    for depth in (True, False):
        g = mig.Gaussians.from_numpy(**params)
        for k in NAMES:
            dr.enable_grad(getattr(g, k))
        dr.eval()
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            out = mig.render(g, cam, background=BACKGROUND, depth=depth)
            dr.eval(out.rgb, out.alpha)
            ops = [k["operation_count"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        loss = (dr.sum(out.rgb.array * mi.Float(weights["rgb"].astype(np.float32).ravel()))
                + dr.sum(out.alpha.array * mi.Float(weights["alpha"].astype(np.float32).ravel())))
        dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        grads = {k: np.array(dr.grad(getattr(g, k))) for k in NAMES}
        got[depth] = (np.array(out.rgb), np.array(out.alpha), grads, out.depth, ops)
    rgb, alpha, grads, depth_img, ops = got[True]
    rgb2, alpha2, grads2, none, ops2 = got[False]
    assert depth_img is not None and none is None
    np.testing.assert_array_equal(rgb2, rgb)
    np.testing.assert_array_equal(alpha2, alpha)
    for k in NAMES:
        np.testing.assert_array_equal(grads2[k], grads[k], err_msg=k)
    if name != "empty":
        assert sum(ops2) < sum(ops)      # (the blend loop's kernel: fewer operations; the others the same)
    plain = mig.render(mig.Gaussians.from_numpy(**params), cam, background=BACKGROUND, depth=False)  # (no AD)
    assert plain.depth is None
    np.testing.assert_array_equal(np.array(plain.rgb), rgb)
    np.testing.assert_array_equal(np.array(plain.alpha), alpha)


@pytest.mark.parametrize("threads", [None, 1, 3])
def test_tiles_ordered_by_work_keep_their_bands_longest_list_first(threads):
    """``LaneLayout.by_work`` (the CPU's): every tile in one slot, the other slots padding (``n_tiles``); the tiles of
    a band of BAND_ROWS tile rows in a contiguous run of slots, in decreasing order of their lists' lengths (to the
    order's resolution, 1/8 of a doubling), equal levels in image order; with up to two blocks per thread (Dr.Jit's
    LLVM backend cuts a kernel into 2 per thread, padded here to equal lengths), band b in block b % blocks."""
    import mitsuba as mi

    from mi_gaussians.raster.binning import Bins
    from mi_gaussians.raster.blend import BAND_ROWS, slot_count, tile_slots

    rng = np.random.default_rng(5)
    tiles_x, tiles_y = 13, 9                       # (a partial last band)
    n = tiles_x * tiles_y
    lengths = rng.integers(0, 3000, n)
    lengths[rng.random(n) < 0.3] = 0
    lengths[:4] = 200                              # (equal lengths in one band)
    bins = Bins(gaussian=dr.zeros(mi.UInt32, 1), tile_start=mi.UInt32(np.concatenate([[0], np.cumsum(lengths)])),
                n_instances=int(lengths.sum()), tiles_x=tiles_x, tiles_y=tiles_y)
    before = dr.thread_count()
    try:
        if threads:
            dr.set_thread_count(threads)
        cores = dr.thread_count()
        slots = tile_slots(bins, LANE_LAYOUTS["llvm"]).numpy()
        assert len(slots) == slot_count(tiles_x, tiles_y, LANE_LAYOUTS["llvm"])
    finally:
        dr.set_thread_count(before)
    assert LANE_LAYOUTS["llvm"].by_work
    real = slots < n
    assert sorted(slots[real]) == list(range(n)) and (slots[~real] == n).all()
    band_tiles = tiles_x * BAND_ROWS
    blocks = 2 * cores if cores > 1 else 1
    assert len(slots) % blocks == 0
    for band in range(-(-tiles_y // BAND_ROWS)):
        pos = np.flatnonzero(real & (slots // band_tiles == band))
        assert len(pos) == min(band_tiles, n - band * band_tiles)
        assert pos[-1] - pos[0] + 1 == len(pos), f"band {band} is not one run of slots"
        if blocks > 1:
            assert pos[0] // (len(slots) // blocks) == band % blocks
        run = lengths[slots[pos]]
        assert (run[1:] < (run[:-1] + 1) * 2 ** (1 / 8)).all(), f"band {band}: {run}"
        equal = run[1:] == run[:-1]
        assert (slots[pos][1:][equal] > slots[pos][:-1][equal]).all()
    # without by_work, the image's order, which the order test above fails on these lengths
    plain = tile_slots(bins, LaneLayout(pixels=8, start_lanes=8, tile_rows=8, tile_cols=8)).numpy()
    assert (plain == np.arange(n)).all()
    assert not (lengths[1:band_tiles] < (lengths[:band_tiles - 1] + 1) * 2 ** (1 / 8)).all()


def test_lane_layout_rejects_what_the_kernels_cannot_map():
    with pytest.raises(ValueError, match="pixels = 3"):
        LaneLayout(pixels=3, start_lanes=16)
    with pytest.raises(ValueError, match="start_lanes = 64"):
        LaneLayout(pixels=8, start_lanes=64, tile_rows=16)   # a 16 x 16 tile has 32 lanes of 8 pixels
    with pytest.raises(ValueError, match="tile_rows = 12"):
        LaneLayout(pixels=4, start_lanes=16, tile_rows=12)
    with pytest.raises(ValueError, match="pixels = 8"):
        LaneLayout(pixels=8, start_lanes=16, tile_rows=4)    # a lane's pixels lie in one tile column
    with pytest.raises(ValueError, match="tile_cols = 12"):
        LaneLayout(pixels=4, start_lanes=16, tile_rows=8, tile_cols=12)
    with pytest.raises(ValueError, match="start_lanes = 16"):
        LaneLayout(pixels=8, start_lanes=16, tile_rows=8, tile_cols=8)   # an 8 x 8 tile has 8 lanes of 8 pixels
    assert LaneLayout(pixels=4, start_lanes=16, tile_rows=4).tiles(53, 37) == (4, 10)
    assert LaneLayout(pixels=8, start_lanes=8, tile_rows=8, tile_cols=8).tiles(53, 37) == (7, 5)
    assert LaneLayout(pixels=8, start_lanes=8, tile_rows=8, tile_cols=8).tile == (8, 8)


@pytest.mark.parametrize("layout", ["llvm", "cuda"])
def test_a_render_reports_its_heaviest_tile(layout):
    """``out.max_tile``: the most instances blended in one tile. Three small Gaussians inside the first tile (of 8 x 8
    and of 16 x 16 pixels alike), one alone in another: 3 of 4; an empty scene: 0."""
    cam = sf.generic_camera(64, 48)
    px, py, z = np.array([2.5, 4.5, 3.5, 44.5]), np.array([2.5, 3.5, 4.5, 20.5]), np.array([3.0, 4.0, 5.0, 3.5])
    n = len(px)
    scales = np.repeat(np.log(0.4 * z / cam.fx)[:, None], 3, axis=1)       # 0.4 pixels: ~2.5 pixels of alpha >= 1/255
    dc, _ = sf.random_sh(np.random.default_rng(0), n, 0)
    params = sf.make_params(sf.pixel_to_world(cam, px, py, z), scales, np.tile([1.0, 0, 0, 0], (n, 1)),
                            np.full(n, 3.0), dc)
    out = mig.render(mig.Gaussians.from_numpy(**params), cam, layout=LANE_LAYOUTS[layout])
    assert int(out.n_blended[0]) == 4 and int(out.max_tile[0]) == 3
    empty = mig.render(mig.Gaussians.from_numpy(**sf.empty_scene()[0]), cam, layout=LANE_LAYOUTS[layout])
    assert int(empty.max_tile[0]) == 0


def test_the_balanced_layout_follows_the_heaviest_tiles_share():
    """On CUDA, the most pixels per lane whose heaviest tile's lanes stay within BALANCE times the mean resident lane's
    work: for the heaviest tile's share of the instances counted here on the cases timed on an H200 (a 7k
    mi_objects/colmap model at 200, 400 and 800 pixels square; synthetic scenes), the layout that was fastest there
    (docs/benchmarks/gpu.md); fewer pixels as the share grows; on the CPU, its one layout whatever the share."""
    from mi_gaussians.raster.blend import CUDA_LAYOUTS, balanced_layout

    # (the heaviest tile's instances, all tiles' instances, pixels per lane of the fastest layout on the H200)
    timed = [(4796, 101_288, 1), (2216, 167_300, 1), (1202, 362_550, 1), (256, 558_825, 4), (546, 2_849_064, 4),
             (1440, 14_460_546, 4), (501, 274_670, 2), (164, 82_642, 2)]
    for heaviest, total, pixels in timed:
        assert balanced_layout(heaviest / total, cuda=True).pixels == pixels, (heaviest, total)
    chosen = [balanced_layout(s, cuda=True) for s in np.geomspace(1e-7, 1.0, 300)]
    assert all(c in CUDA_LAYOUTS for c in chosen)
    assert [c.pixels for c in chosen] == sorted((c.pixels for c in chosen), reverse=True)
    assert {c.pixels for c in chosen} == {4, 2, 1} and chosen[0] == LANE_LAYOUTS["cuda"]
    assert balanced_layout(0.0, cuda=False) == balanced_layout(1.0, cuda=False) == LANE_LAYOUTS["llvm"]


def test_the_cpu_trains_small_gaussians_on_small_tiles():
    """On the CPU: SMALL_TILES (4 x 8) while the visible Gaussians' mean footprint radius is below SMALL_RADIUS
    pixels, the 8 x 8 layout above it or when unknown; whatever the heaviest tile's share. CUDA's choice ignores it."""
    from mi_gaussians.raster.blend import SMALL_RADIUS, SMALL_TILES, balanced_layout

    assert SMALL_TILES.tile == (4, 8) and SMALL_TILES.by_work and LANE_LAYOUTS["llvm"].tile == (8, 8)
    for share in (0.0, 0.3, 1.0):
        assert balanced_layout(share, cuda=False, radius=0.5 * SMALL_RADIUS) == SMALL_TILES
        assert balanced_layout(share, cuda=False, radius=2.0 * SMALL_RADIUS) == LANE_LAYOUTS["llvm"]
        assert balanced_layout(share, cuda=False, radius=None) == LANE_LAYOUTS["llvm"]
        assert balanced_layout(share, cuda=True, radius=1.0) == balanced_layout(share, cuda=True)


#: a CPU layout whose backward skips (as CUDA's do)
SKIPPING = LaneLayout(pixels=8, start_lanes=8, tile_rows=8, tile_cols=8, skip=True)


@pytest.mark.parametrize("footprint", ["box", "ellipse"])
@pytest.mark.parametrize("alpha_min", [1.0 / 255.0, 1e-6, 0.2])
def test_the_backward_packet_skip_changes_no_gradient(monkeypatch, ordered_sums, footprint, alpha_min):
    """With ``LaneLayout.skip`` (CUDA's layouts; here on a CPU layout that skips) the backward blend skips an
    instance's arithmetic in a SIMD packet where no pixel's exponent reaches
    log2(alpha_min / opacity) less ``SKIP_MARGIN``: the gradients are those of the loop that never skips, at every
    alpha_min, with fully transparent Gaussians and with the box footprint (many binned
    tiles no pixel of which is reached). A bound that skips reachable pixels (a negative margin) changes them.
    (In a fixed order of sums, ``ordered_sums``: on two threads the rounding of the two runs' sums once differed by
    1.03e-6 of the largest gradient, above the tolerance, in a clean-clone CI run.)"""
    from mi_gaussians.config import RasterConfig

    monkeypatch.setattr(blend_module, "lane_layout", lambda: SKIPPING)
    params, cam = sf.random_scene(seed=41, n=120, sh_degree=1, width=61, height=43)
    params["opacities"][::7] = -1e4        # opacity 0 in float32
    params["opacities"][3::7] = -4.0       # alpha near 1/255 at the centre: the bound's edge
    weights = random_weights(cam, seed=5)
    cfg = RasterConfig(footprint=footprint, alpha_min=alpha_min)
    skipping = gradients_numpy(params, cam, weights, background=BACKGROUND, cfg=cfg)[0]
    monkeypatch.setattr(blend_module, "SKIP_MARGIN", float("inf"))     # lo = -inf: never skip
    never = gradients_numpy(params, cam, weights, background=BACKGROUND, cfg=cfg)[0]
    for k in NAMES:
        scale = max(np.abs(never[k]).max(), 1e-6)
        np.testing.assert_allclose(skipping[k], never[k], rtol=0, atol=1e-6 * scale, err_msg=k)
    # skips pixels of alpha up to 8 alpha_min (at alpha_min 1e-6, up to 0.07: those below carry no visible weight)
    monkeypatch.setattr(blend_module, "SKIP_MARGIN", -3.0 if alpha_min > 1e-3 else -16.0)
    wrong = gradients_numpy(params, cam, weights, background=BACKGROUND, cfg=cfg)[0]
    assert any(not np.allclose(wrong[k], never[k], rtol=0, atol=1e-4 * max(np.abs(never[k]).max(), 1e-6))
               for k in NAMES)


@pytest.mark.parametrize("footprint", ["box", "ellipse"])
@pytest.mark.parametrize("alpha_min", [1.0 / 255.0, 1e-6, 0.2])
@pytest.mark.parametrize("layout", ["llvm", "skipping"])
def test_every_alpha_min_has_the_loop_ads_gradients(footprint, alpha_min, layout, monkeypatch):
    """At every ``raster.alpha_min``, with fully transparent Gaussians and Gaussians whose alpha is near alpha_min at
    their centre, and with both footprints (the box bins many tiles no pixel of which is reached): the hand-written
    backward's gradients are those of Dr.Jit's AD through the brute-force per-pixel loop, with the CPU's layout
    (no skip) and with one that skips."""
    from mi_gaussians.config import RasterConfig

    params, cam = sf.random_scene(seed=41, n=60, sh_degree=1, width=41, height=29)
    params["opacities"][::7] = -1e4        # opacity 0 in float32
    params["opacities"][3::7] = -4.0       # alpha near 1/255 at the centre
    weights = random_weights(cam, seed=5)
    cfg = RasterConfig(footprint=footprint, alpha_min=alpha_min)
    monkeypatch.setattr(blend_module, "lane_layout", lambda: SKIPPING if layout == "skipping" else LANE_LAYOUTS["llvm"])
    _assert_matches_loop_ad(params, cam, weights, cfg=cfg)
