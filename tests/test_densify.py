"""Adaptive density control (mi_gaussians.optim.densify.DefaultStrategy) on crafted scenes.

The render output is faked (``radii`` and ``means2d_grad`` set by hand) so that every rule is hit on purpose:
NDC scaling of the pixel gradient, visibility-gated statistics, clone / split / prune counts, exact copies, split
sampling statistics, the opacity reset and its schedule (off with interval 0), world-size pruning after
``prune_large_after`` and the optional screen-size pruning relative to the image size, and the Adam state carried
through every change. One test drives the strategy with the real rasterizer.
"""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from kernel_log import KernelLog
from mi_gaussians.config import DensifyConfig, OptimConfig
from mi_gaussians.drjit_utils import owned_array
from mi_gaussians.model.gaussians import PARAMETER_NAMES, Gaussians
from mi_gaussians.optim.adam import GaussianAdam
from mi_gaussians.optim.densify import DefaultStrategy, DensifyState
from mi_gaussians.optim.strategy import StepInfo, Strategy

#: The 2023 reference's schedule of opacity resets, stated here so that these tests do not depend on the default
RESETS = dict(opacity_reset_interval=3000)
EXTENT = 2.0           # clone/split boundary: 0.01 * 2 = 0.02; world-size prune: 0.1 * 2 = 0.2
W = H = 100            # NDC factor 50: pixel gradient 1e-5 -> 5e-4 (dense), 1e-6 -> 5e-5 (not)
HIGH, LOW = 1e-5, 1e-6


@dataclasses.dataclass
class FakeOut:
    """What the strategy reads from a RenderOutput: radii, means2d_grad and the image size (rgb.shape)."""
    radii: "mi.Int32"
    means2d_grad: "mi.Vector2f"
    rgb: "mi.TensorXf"


def fake_out(radii, gx, gy=None, width=W, height=H) -> FakeOut:
    gx = np.asarray(gx, np.float32)
    gy = np.zeros_like(gx) if gy is None else np.asarray(gy, np.float32)
    return FakeOut(mi.Int32(np.asarray(radii, np.int32)), mi.Vector2f(mi.Float(gx), mi.Float(gy)),
                   mi.TensorXf(dr.zeros(mi.Float, height * width * 3), (height, width, 3)))


def logit(p):
    return math.log(p / (1.0 - p))


def quat_to_matrix(q):
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def build(rows, seed=0):
    """Gaussians from a list of dicts (sigma: scalar or 3-vector, opacity, optional quat); degree 1 SH, owned by a
    GaussianAdam with nonzero Adam moments (t = 5) installed on every parameter."""
    rng = np.random.default_rng(seed)
    n = len(rows)
    sig = np.array([np.broadcast_to(np.asarray(r["sigma"], np.float64), 3) for r in rows])
    quats = np.array([r.get("quat", rng.normal(size=4)) for r in rows])
    g = Gaussians.from_numpy(rng.normal(size=(n, 3)), np.log(sig), quats,
                             np.array([logit(r["opacity"]) for r in rows]), rng.normal(size=(n, 3)),
                             rng.normal(size=(n, 3, 3)))
    params = GaussianAdam(g, OptimConfig(), EXTENT)
    state = {}
    for key in PARAMETER_NAMES:
        shape = tuple(params[key].shape)
        state[f"{key}.t"] = np.array([5], np.uint32)
        state[f"{key}.m"] = rng.normal(size=shape).astype(np.float32)
        state[f"{key}.v"] = rng.uniform(0.1, 1.0, size=shape).astype(np.float32)
    params.import_moments(state)
    return params


def snapshot(params) -> dict:
    out = {}
    for key in PARAMETER_NAMES:
        t, m, v = params.moments(key)
        out[key] = dict(value=np.array(params[key]).reshape(tuple(params[key].shape)), m=m, v=v, t=t)
    return out


def stats(s: DefaultStrategy, st: DensifyState) -> dict:
    return s.export_state(st)[0]


# The crafted scene: (row, pixel gradient x, radius)
SCENE = [
    (dict(sigma=0.01, opacity=0.5), HIGH, 5),                                  # 0 clone
    (dict(sigma=(0.05, 0.03, 0.04), opacity=0.6), HIGH, 8),                    # 1 split
    (dict(sigma=0.01, opacity=0.5), LOW, 5),                                   # 2 untouched
    (dict(sigma=0.01, opacity=0.001), LOW, 3),                                 # 3 pruned (opacity)
    (dict(sigma=0.01, opacity=0.5), 1e-3, 0),                                  # 4 invisible: its gradient is ignored
    (dict(sigma=0.3, opacity=0.5), LOW, 10),                                   # 5 world-huge (pruned after 3000)
    (dict(sigma=0.01, opacity=0.5), LOW, 30),                                  # 6 screen-huge: 0.3 of W = H = 100
                                                                               # (pruned after 3000 when that is on)
    (dict(sigma=0.01, opacity=0.003), HIGH, 5),                                # 7 cloned, then it and its clone pruned
]


def crafted():
    params = build([r for r, _, _ in SCENE])
    out = fake_out([r for _, _, r in SCENE], [gx for _, gx, _ in SCENE])
    return params, out


# ---------------------------------------------------------------------------------------------- statistics
def test_statistics_ndc_scaling_visibility_and_max_screen():
    params = build([dict(sigma=0.01, opacity=0.5)] * 3)
    s = DefaultStrategy(DensifyConfig(), EXTENT)
    state = s.initialize_state(params.n)
    info = s.step_post_backward(params, state, 10,
                                fake_out([4, 0, 7], [3e-6, 1.0, -1e-6], [4e-6, 1.0, 2e-6], width=200, height=100))
    assert not info.changed and info.n == 3
    st = stats(s, state)
    # (gx * W/2, gy * H/2) = (3e-4, 2e-4) for W = 200, H = 100
    np.testing.assert_allclose(st["grad_accum"], [math.hypot(3e-4, 2e-4), 0.0, math.hypot(1e-4, 1e-4)], rtol=1e-6)
    np.testing.assert_array_equal(st["denom"], [1, 0, 1])
    # radii as a fraction of the view's max(W, H) = 200
    np.testing.assert_allclose(st["max_screen"], [4 / 200, 0, 7 / 200], rtol=1e-6)
    s.step_post_backward(params, state, 11, fake_out([2, 9, 8], [0.0, 0.0, 0.0], width=200, height=100))
    st = stats(s, state)
    np.testing.assert_array_equal(st["denom"], [2, 1, 2])
    np.testing.assert_allclose(st["max_screen"], [4 / 200, 9 / 200, 8 / 200], rtol=1e-6)
    # a view of another size: its radii count relative to its own size (12 px of 60 = 0.2)
    s.step_post_backward(params, state, 12, fake_out([12, 1, 1], [0.0, 0.0, 0.0], width=40, height=60))
    np.testing.assert_allclose(stats(s, state)["max_screen"], [0.2, 9 / 200, 8 / 200], rtol=1e-6)


def test_mean_gradient_counts_only_visible_iterations():
    """Two visible iterations at 2.5e-4 (NDC) and one invisible one: mean 2.5e-4 >= 2e-4 -> clone (had the
    invisible iteration counted, the mean would be 1.67e-4 and nothing would happen)."""
    params = build([dict(sigma=0.01, opacity=0.5), dict(sigma=0.01, opacity=0.5)])
    s = DefaultStrategy(DensifyConfig(), EXTENT)
    state = s.initialize_state(params.n)
    px = 2.5e-4 / (W / 2)
    s.step_post_backward(params, state, 598, fake_out([3, 3], [px, px / 2]))
    s.step_post_backward(params, state, 599, fake_out([0, 3], [0.0, px / 2]))
    info = s.step_post_backward(params, state, 600, fake_out([3, 3], [px, px / 2]))
    assert (info.cloned, info.split, info.pruned) == (1, 0, 0) and params.n == 3


# ---------------------------------------------------------------------------------------------- densify and prune
def test_clone_split_prune_counts_values_and_moments():
    params, out = crafted()
    before = snapshot(params)
    s = DefaultStrategy(DensifyConfig(), EXTENT)
    state = s.initialize_state(params.n)
    info = s.step_post_backward(params, state, 600, out)
    assert info == StepInfo(cloned=2, split=1, pruned=3, reset=0, densified=True, opacity_reset=False, changed=True, n=8)
    after = snapshot(params)
    view = params.gaussians
    assert params.n == 8 and all(getattr(view, k) is params[k] for k in PARAMETER_NAMES)

    # layout: kept originals [0, 2, 4, 5, 6], clone of 0, the two children of 1 (clone of 7 and 7 itself pruned)
    kept = [0, 2, 4, 5, 6]
    for key in PARAMETER_NAMES:
        a, b = after[key], before[key]
        assert a["t"] == 5                                           # the step count carries on
        for f in ("value", "m", "v"):
            np.testing.assert_array_equal(a[f][:5], b[f][kept])      # survivors: bit-identical values and moments
        np.testing.assert_array_equal(a["value"][5], b["value"][0])  # the clone is an exact copy
        assert not a["m"][5:].any() and not a["v"][5:].any()         # new rows: zero moments
    for key in ("rotations", "opacities", "sh_dc", "sh_rest"):       # children copy everything but means and scales
        for c in (6, 7):
            np.testing.assert_array_equal(after[key]["value"][c], before[key]["value"][1])
    np.testing.assert_allclose(np.exp(after["scales"]["value"][6:]), np.exp(before["scales"]["value"][[1, 1]]) / 1.6,
                               rtol=1e-6)
    # the split original is gone; its children were sampled around it (within a few sigma), not on it
    means = after["means"]["value"]
    parent = before["means"]["value"][1]
    assert not np.any(np.all(means == parent, axis=1))
    assert np.all(np.abs(means[6:] - parent) < 5 * 0.05) and np.all(means[6] != means[7])
    # statistics reset for all remaining rows
    st = stats(s, state)
    assert len(st["grad_accum"]) == 8 and not st["grad_accum"].any() and not st["denom"].any()
    assert not st["max_screen"].any()


def present_after(step, cfg, out=None, warmup=None, empty=False):
    """Whether the world-huge row 5 and the screen-huge row 6 of the crafted scene survive a densification at
    ``step`` (after one statistics-only iteration ``warmup`` when given; ``empty``: on an empty background), and the
    step's info."""
    params, crafted_out = crafted()
    s = DefaultStrategy(cfg, EXTENT, empty_background=empty)
    state = s.initialize_state(params.n)
    if warmup is not None:
        s.step_post_backward(params, state, warmup, crafted_out)
    before = snapshot(params)
    info = s.step_post_backward(params, state, step, out or crafted_out)
    means = snapshot(params)["means"]["value"]
    return [bool(np.any(np.all(means == before["means"]["value"][i], axis=1))) for i in (5, 6)], info


def test_big_gaussians_pruned_only_after_prune_large_after():
    screen = dataclasses.replace(DensifyConfig(**RESETS), max_screen_fraction=0.2)
    present, info = present_after(3000, screen)
    assert info.pruned == 3 and present == [True, True] and info.opacity_reset
    # the screen-size test uses the largest radius since the last densification, not the last one
    smaller = fake_out([r if i != 6 else 2 for i, (_, _, r) in enumerate(SCENE)], [gx for _, gx, _ in SCENE])
    present, info = present_after(3100, screen, smaller, warmup=3050)
    assert info.pruned == 5 and present == [False, False]
    # the start is a setting of its own: resets off (interval 0) keeps the prunes, prune_large_after moves them
    present, info = present_after(3100, dataclasses.replace(screen, opacity_reset_interval=0))
    assert info.pruned == 5 and present == [False, False]
    present, info = present_after(3100, dataclasses.replace(screen, prune_large_after=5000))
    assert info.pruned == 3 and present == [True, True]


def test_screen_size_prune_is_off_by_default_like_the_reference():
    """The reference's 20 px test never fires (its densification_postfix zeroes max_radii2D first): by default only
    the world-size test prunes large Gaussians."""
    assert DensifyConfig().max_screen_fraction == 0
    present, info = present_after(3100, DensifyConfig())
    assert info.pruned == 4 and present == [False, True]     # 3, 7, clone of 7 and the world-huge 5; 6 stays


def test_screen_size_prune_is_relative_to_the_image():
    """The same Gaussian, 30 px across in views of 100 and of 200 pixels: a fraction of 0.2 prunes it in the first
    (0.3 of the image) and not in the second (0.15), where a rule in pixels would prune both; max(W, H) counts."""
    cfg = dataclasses.replace(DensifyConfig(), max_screen_fraction=0.2)
    radii, grads = [r for _, _, r in SCENE], [gx for _, gx, _ in SCENE]
    for width, height, pruned in ((100, 100, True), (200, 200, False), (200, 50, False), (50, 120, True)):
        present, _ = present_after(3100, cfg, fake_out(radii, grads, width=width, height=height))
        assert present[1] is not pruned, (width, height)


def test_on_an_empty_background_the_screen_size_prune_is_on_at_its_own_fraction():
    """An object on an empty background (issue 52): the screen-size test prunes at ``empty_screen_fraction`` when
    ``max_screen_fraction`` is 0, in the span after ``prune_large_after``; ``max_screen_fraction`` > 0 sets the
    threshold; ``empty_screen_fraction`` 0 turns it off; not on an empty background, the reference (no prune)."""
    cfg = DensifyConfig()
    assert cfg.empty_screen_fraction == 0.1 and cfg.screen_prune_span == 500 and cfg.max_screen_fraction == 0
    assert DefaultStrategy(cfg, EXTENT, empty_background=True).screen_fraction == 0.1
    assert DefaultStrategy(cfg, EXTENT).screen_fraction == 0

    def screen_huge_kept(cfg, empty, step=3100, size=100):       # row 6: 30 px, 0.3 of a 100-pixel view
        radii, grads = [r for _, _, r in SCENE], [gx for _, gx, _ in SCENE]
        return present_after(step, cfg, fake_out(radii, grads, width=size, height=size), empty=empty)[0][1]

    assert not screen_huge_kept(cfg, True)                                # 0.3 > 0.1: pruned
    assert not screen_huge_kept(cfg, True, size=200)                      # 0.15 > 0.1
    assert screen_huge_kept(cfg, True, size=400)                          # 0.075 of a 400-pixel view: kept
    assert screen_huge_kept(cfg, False)                                   # the reference: kept
    assert screen_huge_kept(cfg, True, step=3600)                         # past the span of 500: kept
    assert screen_huge_kept(dataclasses.replace(cfg, empty_screen_fraction=0.0), True)
    assert screen_huge_kept(dataclasses.replace(cfg, max_screen_fraction=0.2), True, size=200)   # its own: 0.15
    assert not screen_huge_kept(dataclasses.replace(cfg, max_screen_fraction=0.2), False)        # 0.3 > 0.2


def test_the_screen_size_prune_can_be_held_to_a_span_after_prune_large_after():
    """With ``screen_prune_span`` the screen-size test prunes only in the densifications of that many iterations
    after ``prune_large_after`` (gsplat's refine_scale2d_stop_iter); the world-size test goes on."""
    cfg = dataclasses.replace(DensifyConfig(), max_screen_fraction=0.2, screen_prune_span=500)
    present, _ = present_after(3500, cfg)
    assert present == [False, False]                       # (3000 + 500: the last densification it prunes in)
    present, _ = present_after(3600, cfg)
    assert present == [False, True]                        # (only the world-huge 5 is pruned)
    present, _ = present_after(3600, dataclasses.replace(cfg, screen_prune_span=0))
    assert present == [False, False]                       # (0: every densification)


def test_split_sampling_statistics():
    """Many children of one Gaussian: sample mean ~ centre, covariance ~ R S S^T R^T, scales sigma / 1.6."""
    k = 20000
    q = np.array([0.8, -0.4, 0.9, 0.3]) * 2.0          # unnormalized on purpose
    sigma = np.array([0.3, 0.1, 0.05])
    params = build([dict(sigma=sigma, opacity=0.5, quat=q)])
    centre = np.array(params["means"]).reshape(3).astype(np.float64)
    s = DefaultStrategy(dataclasses.replace(DensifyConfig(), split_count=k), 1.0, seed=3)
    state = s.initialize_state(params.n)
    info = s.step_post_backward(params, state, 600, fake_out([5], [HIGH]))
    assert info.split == 1 and info.cloned == 0 and params.n == k
    x = np.array(params["means"]).reshape(k, 3).astype(np.float64)
    R = quat_to_matrix(q)
    cov_ref = R @ np.diag(sigma ** 2) @ R.T
    L = np.linalg.cholesky(cov_ref)
    z = np.linalg.solve(L, (x - centre).T).T          # whitened: ~ N(0, I)
    assert np.all(np.abs(z.mean(axis=0)) < 5 / math.sqrt(k))
    np.testing.assert_allclose(np.cov(z.T), np.eye(3), atol=5 * math.sqrt(2 / k))
    np.testing.assert_allclose(np.exp(np.array(params["scales"]).reshape(k, 3)), np.tile(sigma / 1.6, (k, 1)),
                               rtol=1e-5)
    # kurtosis check against a merely decorrelated but non-Gaussian sampler
    np.testing.assert_allclose((z ** 4).mean(axis=0), 3.0, atol=0.2)


def test_split_samples_are_seeded_and_fresh_per_densification():
    def children(seed, calls):
        params = build([dict(sigma=0.05, opacity=0.5)])
        s = DefaultStrategy(DensifyConfig(), EXTENT, seed=seed)
        state = s.initialize_state(params.n)
        for step in range(600, 600 + 100 * calls, 100):
            s.step_post_backward(params, state, step, fake_out(np.full(params.n, 5), np.full(params.n, HIGH)))
        return np.array(params["means"]).reshape(-1, 3)

    a, b, c = children(0, 1), children(0, 1), children(1, 1)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    two = children(0, 2)     # the second densification splits both children with fresh draws
    assert len(two) == 4 and len(np.unique(two, axis=0)) == 4


# ---------------------------------------------------------------------------------------------- opacity reset
def test_opacity_reset_values_and_moments():
    ops = [0.5, 0.9, 0.007, 0.011, 0.02]
    params = build([dict(sigma=0.01, opacity=p) for p in ops])
    before = snapshot(params)
    s = DefaultStrategy(DensifyConfig(**RESETS), EXTENT)
    state = s.initialize_state(params.n)
    info = s.step_post_backward(params, state, 3000, fake_out(np.full(5, 3), np.full(5, LOW)))
    assert info.opacity_reset and info.densified and info.reset == 4
    assert (info.cloned, info.split, info.pruned) == (0, 0, 0)
    after = snapshot(params)
    o = after["opacities"]["value"]
    np.testing.assert_allclose(1 / (1 + np.exp(-o.astype(np.float64))), [0.01, 0.01, 0.007, 0.01, 0.01], rtol=1e-5)
    assert o[2] == before["opacities"]["value"][2]                 # already below: untouched
    assert after["opacities"]["t"] == 5 and not after["opacities"]["m"].any() and not after["opacities"]["v"].any()
    assert params.gaussians.opacities is params["opacities"] and dr.grad_enabled(params["opacities"])
    for key in ("means", "scales", "rotations", "sh_dc", "sh_rest"):  # nothing else touched
        for f in ("value", "m", "v"):
            np.testing.assert_array_equal(after[key][f], before[key][f])


def test_reset_once_lowers_each_gaussian_at_its_first_reset_only():
    """``reset_once``: the first reset lowers every row (values and moments as the reference's reset); the next one
    lowers only the rows created since (a clone, even of a reset row, is new) and leaves the others' values and
    moments bit-identical; the marks follow the rows through clones, splits and prunes and through a checkpoint.
    Off (the default), the second reset lowers every row again."""
    def run(once):
        params, out = crafted()
        s = DefaultStrategy(DensifyConfig(**RESETS, reset_once=once), EXTENT)
        state = s.initialize_state(params.n)
        first = s.step_post_backward(params, state, 3000, out)      # densify (8 rows: see above), then reset all
        assert first.opacity_reset and first.reset == 8 and params.n == 8
        assert stats(s, state)["reset_done"].all()
        # opacities recover; at the next densification the world-huge row goes and a clone of row 0 comes
        o = np.array(params["opacities"]).copy()
        o[:] = logit(0.6)
        params.replace("opacities", mi.TensorXf(mi.Float(o.astype(np.float32)), (params.n,)))
        grads = np.full(params.n, LOW)
        grads[0] = HIGH
        s.step_post_backward(params, state, 3100, fake_out(np.full(params.n, 3), grads))
        assert params.n == 8 and stats(s, state)["reset_done"].tolist() == [True] * 7 + [False]
        arrays, meta = s.export_state(state)                         # the marks survive a checkpoint
        s2 = DefaultStrategy(DensifyConfig(**RESETS, reset_once=once), EXTENT)
        state2 = s2.import_state(arrays, meta, params.n)
        np.testing.assert_array_equal(stats(s2, state2)["reset_done"], arrays["reset_done"])
        moments = params.export_moments()           # (the first reset zeroed them: give the second some to keep)
        for f, lo in (("m", -1.0), ("v", 0.1)):
            moments[f"opacities.{f}"] = np.random.default_rng(1).uniform(lo, 1.0, params.n).astype(np.float32)
        params.import_moments(moments)
        before = snapshot(params)
        second = s2.step_post_backward(params, state2, 6000, fake_out(np.full(params.n, 3), np.full(params.n, LOW)))
        return second, before, snapshot(params), stats(s2, state2)

    second, before, after, st = run(True)
    assert second.reset == 1 and st["reset_done"].all()
    p = 1 / (1 + np.exp(-after["opacities"]["value"].astype(np.float64)))
    np.testing.assert_allclose(p, [0.6] * 7 + [0.01], rtol=1e-5)
    for f in ("m", "v"):     # the rows it spared keep their moments; the new row's (zero anyway) are zeroed
        np.testing.assert_array_equal(after["opacities"][f][:7], before["opacities"][f][:7])
        assert not after["opacities"][f][7:].any()
    second, _, after, _ = run(False)
    assert second.reset == 8
    np.testing.assert_allclose(1 / (1 + np.exp(-after["opacities"]["value"].astype(np.float64))), 0.01, rtol=1e-5)


@pytest.mark.parametrize("white, step, every, expect", [
    (True, 500, 3000, True), (False, 500, 3000, False), (True, 600, 3000, False), (False, 6000, 3000, True),
    (False, 15000, 3000, False), (True, 500, 0, False), (False, 3000, 0, False), (False, 6000, 0, False)])
def test_opacity_reset_schedule(white, step, every, expect):
    """Every ``every`` iterations while densifying, and at densify_from_iter on a white background (the reference);
    never with an interval of 0 (gsplat 1.5.3 as it runs)."""
    params = build([dict(sigma=0.01, opacity=0.5)] * 2)
    s = DefaultStrategy(DensifyConfig(opacity_reset_interval=every), EXTENT, white_background=white)
    info = s.step_post_backward(params, s.initialize_state(params.n), step, fake_out([3, 3], [LOW, LOW]))
    assert info.opacity_reset == expect
    p = 1 / (1 + np.exp(-np.array(params["opacities"], np.float64)))
    np.testing.assert_allclose(p, 0.01 if expect else 0.5, rtol=1e-5)


@pytest.mark.parametrize("white, empty, expect", [(False, False, False), (True, False, True), (False, True, True),
                                                   (True, True, True)])
def test_on_an_empty_background_the_opacities_are_reset_at_densify_from_iter(white, empty, expect):
    """The reference resets at densify_from_iter on a white background, where the random points' floaters show;
    on an empty background they show over any colour (issue 52), so the reset comes there too."""
    params = build([dict(sigma=0.01, opacity=0.5)] * 2)
    s = DefaultStrategy(DensifyConfig(), EXTENT, white_background=white, empty_background=empty)
    assert s.refines_at(500) == expect
    info = s.step_post_backward(params, s.initialize_state(params.n), 500, fake_out([3, 3], [LOW, LOW]))
    assert info.opacity_reset == expect


def test_nothing_happens_from_densify_until_iter_on():
    params, out = crafted()
    s = DefaultStrategy(DensifyConfig(), EXTENT)
    state = s.initialize_state(params.n)
    for step in (15000, 15100, 18000):
        info = s.step_post_backward(params, state, step, out)
        assert not info.changed and params.n == 8
    assert not stats(s, state)["denom"].any()       # no statistics either
    info = s.step_post_backward(params, state, 14900, out)
    assert info.densified and info.cloned == 2


def test_densification_schedule_and_state_size_check():
    params, out = crafted()
    s = DefaultStrategy(DensifyConfig(), EXTENT)
    state = s.initialize_state(params.n)
    assert not s.step_post_backward(params, state, 500, out).densified   # iteration > densify_from_iter only
    assert not s.step_post_backward(params, state, 550, out).densified
    assert stats(s, state)["denom"].tolist() == [2, 2, 2, 2, 0, 2, 2, 2]
    with pytest.raises(ValueError, match="render output has 2"):
        s.step_post_backward(params, state, 551, fake_out([1, 1], [0.0, 0.0]))
    with pytest.raises(ValueError, match="statistics cover 3"):
        s.step_post_backward(params, s.initialize_state(3), 552, out)


def test_state_export_import():
    params, out = crafted()
    s = DefaultStrategy(DensifyConfig(), EXTENT, seed=4)
    state = s.initialize_state(params.n)
    s.step_post_backward(params, state, 600, out)
    s.step_post_backward(params, state, 601, fake_out(np.full(8, 6), np.full(8, HIGH * 2, np.float32)))
    arrays, meta = s.export_state(state)
    assert arrays["denom"].tolist() == [1] * 8 and arrays["grad_accum"].max() > 0
    np.testing.assert_allclose(arrays["max_screen"].max(), 6 / W, rtol=1e-6)
    s2 = DefaultStrategy(DensifyConfig(), EXTENT)
    state2 = s2.import_state(arrays, meta, params.n)
    assert s2.seed == 4 and state2.draws == state.draws == 1 and isinstance(state2, DensifyState)
    for k, v in stats(s2, state2).items():
        np.testing.assert_array_equal(v, arrays[k])
    assert stats(s2, s2.import_state({}, {}, 5))["denom"].tolist() == [0] * 5     # no saved statistics: fresh
    with pytest.raises(ValueError, match="lengths"):
        s2.import_state(arrays, meta, 9)
    # a checkpoint of an earlier version (max_radii in pixels, image sizes unknown): the radius statistic restarts
    legacy = {"grad_accum": arrays["grad_accum"], "denom": arrays["denom"], "max_radii": np.full(8, 6, np.int32)}
    st = stats(s2, s2.import_state(legacy, meta, params.n))
    np.testing.assert_array_equal(st["grad_accum"], arrays["grad_accum"])
    assert not st["max_screen"].any()


# ---------------------------------------------------------------------------------------------- real renderer
def test_with_the_real_rasterizer():
    """Render -> backward -> strategy -> Adam step -> render again, with the real RenderOutput."""
    import scene_factory as sf
    from mi_gaussians.raster.rasterize import render

    cam = sf.identity_camera(32, 24, fx=30.0)
    rng = np.random.default_rng(0)
    n = 12
    means = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(2.0, 3.0, n)]
    means[-1] = (0.0, 0.0, -3.0)        # behind the camera: radius 0, never accumulated
    g = Gaussians.from_numpy(means, np.full((n, 3), math.log(0.1)), np.tile([1.0, 0, 0, 0], (n, 1)),
                             np.full(n, 0.5), rng.normal(size=(n, 3)), np.zeros((n, 3, 3)))
    params = GaussianAdam(g, OptimConfig(), 1.0)
    cfg = dataclasses.replace(DensifyConfig(), grad_threshold=1e-12)   # densify every visible Gaussian
    s = DefaultStrategy(cfg, 1.0)
    state = s.initialize_state(params.n)
    for step in (599, 600):
        out = render(params.gaussians, cam)
        s.step_pre_backward(params, state, step, out)
        dr.backward(dr.mean(dr.square(out.rgb.array - 0.25)))
        info = s.step_post_backward(params, state, step, out)
        if step == 599:
            st = stats(s, state)
            assert np.all(st["grad_accum"][:-1] > 0) and st["denom"][-1] == 0 and st["max_screen"][-1] == 0
            assert np.all(st["max_screen"][:-1] > 0)
            params.step()
    assert info.split == n - 1 and info.cloned == 0 and params.n == n + (n - 1)   # sigma 0.1 > 0.01: split
    out = render(params.gaussians, cam)
    dr.backward(dr.mean(dr.square(out.rgb.array - 0.25)))
    params.step()
    assert dr.width(out.radii) == params.n and np.all(np.isfinite(np.array(params["means"])))


def test_gradients_cleared_on_every_densification_iteration():
    """Even when nothing is cloned, split or pruned, a densification iteration leaves no gradient behind (the trainer
    skips the Adam step then, and a stale gradient would be added to the next backward pass)."""
    params = build([dict(sigma=0.01, opacity=0.5)] * 3)
    s = DefaultStrategy(DensifyConfig(), EXTENT)
    state = s.initialize_state(params.n)
    for step, changed in ((650, False), (700, True)):
        g = params.gaussians
        dr.backward(dr.sum(dr.square(g.means.array)) + dr.sum(g.opacities.array) + dr.sum(g.sh_rest.array))
        before = snapshot(params)
        info = s.step_post_backward(params, state, step, fake_out([3, 3, 3], [LOW] * 3))
        assert info.changed == changed and (info.cloned, info.split, info.pruned) == (0, 0, 0)
        if not changed:
            assert np.array(dr.grad(params["means"])).any() and np.array(dr.grad(params["sh_rest"])).any()
            continue
        for key in PARAMETER_NAMES:
            assert not np.array(dr.grad(params[key])).any()
            assert params[key] is getattr(params.gaussians, key)
            np.testing.assert_array_equal(snapshot(params)[key]["m"], before[key]["m"])   # moments untouched


def test_absgrad_statistic_and_threshold():
    """With absgrad the pre-backward hook asks the real backward pass for AbsGS's sums, the statistics accumulate
    them (NDC-scaled like the plain gradient), and densification compares with absgrad_threshold."""
    import scene_factory as sf
    from mi_gaussians.raster.rasterize import render

    cam = sf.identity_camera(32, 24, fx=30.0)
    rng = np.random.default_rng(1)
    n = 10
    means = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(2.0, 3.0, n)]
    g = Gaussians.from_numpy(means, np.full((n, 3), math.log(0.1)), np.tile([1.0, 0, 0, 0], (n, 1)),
                             np.full(n, 0.5), rng.normal(size=(n, 3)), np.zeros((n, 3, 3)))
    accum = {}
    for absgrad in (False, True):
        params = GaussianAdam(g, OptimConfig(), 1.0)
        s = DefaultStrategy(dataclasses.replace(DensifyConfig(), absgrad=absgrad), 1.0)
        state = s.initialize_state(params.n)
        out = render(params.gaussians, cam)
        s.step_pre_backward(params, state, 10, out)
        dr.backward(dr.mean(dr.square(out.rgb.array - 0.25)))
        s.step_post_backward(params, state, 10, out)
        accum[absgrad] = stats(s, state)["grad_accum"]
        if absgrad:
            a = out.means2d_absgrad
            want = np.hypot(np.array(a.x) * 16, np.array(a.y) * 12)      # NDC: W/2 = 16, H/2 = 12
            np.testing.assert_allclose(accum[True], want, rtol=1e-6)
    assert np.all(accum[True] >= accum[False] * (1 - 1e-6)) and np.any(accum[True] > 1.2 * accum[False])
    # no statistics gathered (after densify_until_iter): the backward pass is not asked for the sums
    out = render(params.gaussians, cam)
    s.step_pre_backward(params, state, 20_000, out, collect=s.updates_state_at(20_000))
    with pytest.raises(ValueError, match="request_absgrad"):
        out.means2d_absgrad
    # the threshold: a mean statistic between the two thresholds densifies only in the plain mode
    mid = 5e-4
    for absgrad, expect in ((False, 1), (True, 0)):
        params = build([dict(sigma=0.01, opacity=0.5)])
        s = DefaultStrategy(dataclasses.replace(DensifyConfig(), absgrad=absgrad), EXTENT)
        state = s.initialize_state(1)
        fake = fake_out([3], [mid / (W / 2)])
        if absgrad:
            fake.means2d_absgrad = fake.means2d_grad
        info = s.step_post_backward(params, state, 600, fake)
        assert info.cloned == expect, absgrad


def test_error_gate_densifies_only_the_candidates_whose_score_reaches_it():
    """``densify.error_gate``: of the gradient's candidates, only those whose error score (the strategy's
    ``view_errors``, asked with the model and the iteration) is at least the gate times the mean score are cloned
    or split; pruning is unchanged; 0 (the reference) never asks for the score."""
    scores = np.zeros(len(SCENE), np.float32)
    scores[[1, 7]] = 2e-5                       # the split candidate and the clone candidate that is then pruned
    # (mean score 5e-6: a gate of 3.5 is 1.75e-5, reached; of 4.5, 2.25e-5, not)
    asked = []

    def view_errors(g, step):
        asked.append((g.n, step))
        return mi.Float(scores)

    for gate, expect in ((3.5, dict(cloned=1, split=1, pruned=3)), (4.5, dict(cloned=0, split=0, pruned=2)),
                         (0.0, dict(cloned=2, split=1, pruned=3))):
        params, out = crafted()
        s = DefaultStrategy(dataclasses.replace(DensifyConfig(), error_gate=gate), EXTENT)
        s.view_errors = view_errors
        state = s.initialize_state(params.n)
        info = s.step_post_backward(params, state, 600, out)
        assert (info.cloned, info.split, info.pruned) == (expect["cloned"], expect["split"], expect["pruned"]), gate
    assert asked == [(8, 600), (8, 600)]        # (not with the gate off)
    params, out = crafted()
    s = DefaultStrategy(dataclasses.replace(DensifyConfig(), error_gate=1.0), EXTENT)
    with pytest.raises(ValueError, match="view_errors"):
        s.step_post_backward(params, s.initialize_state(params.n), 600, out)


def test_a_densification_builds_the_same_kernels_whatever_the_counts():
    """Two densifications that clone, split and prune different numbers of rows launch the same kernels: no count
    is a literal in their code (``drjit_utils.concat``), so a training run's refinements reuse the kernels the first
    one built (on CUDA each new kernel costs a compilation)."""
    def densify(copies: int, log: KernelLog) -> set:
        rows = [r for r, _, _ in SCENE] * copies
        params = build(rows, seed=copies)
        out = fake_out([r for _, _, r in SCENE] * copies, [gx for _, gx, _ in SCENE] * copies)
        # (inputs in Dr.Jit's own aligned memory, as a render's are: a zero-copy NumPy buffer's alignment is part of
        # a kernel's code)
        out = FakeOut(owned_array(mi.Int32, np.array(out.radii)),
                      mi.Vector2f(*(owned_array(mi.Float, np.array(c)) for c in out.means2d_grad)), out.rgb)
        s = DefaultStrategy(DensifyConfig(), EXTENT)
        state = s.initialize_state(params.n)
        dr.eval()
        log.cut()
        info = s.step_post_backward(params, state, 600, out)
        snapshot(params)
        assert (info.cloned, info.split, info.pruned) == (2 * copies, copies, 3 * copies)
        return {h for _, h in log.cut()}

    with KernelLog() as log:
        densify(2, log)                          # (warm: every kernel built once)
        first = densify(3, log)
        second = densify(5, log)
    assert first and second == first, (len(first), len(second), len(second - first))
