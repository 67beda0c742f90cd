"""Per-Gaussian blending weights (``mi_gaussians.optim.weights``: the sum over a view's pixels of T * alpha, taken from
the renderer's backward pass, as a share of the view's pixels) against the float64 reference renderer (each Gaussian alone coloured, the rest black:
the image's sum is its weight), and ``densify.weight_prune``, which removes the Gaussians below a threshold."""

from __future__ import annotations

import numpy as np

import mi_gaussians as mig
import scene_factory as sf
from mi_gaussians.optim.weights import max_weights
from reference import render_reference


def alone(n: int, k: int) -> np.ndarray:
    """SH DC of colour 1 for Gaussian ``k`` and 0 for the others."""
    return np.repeat(np.where(np.arange(n)[:, None] == k, 0.5, -0.5) / sf.SH_C0, 3, axis=1)


def test_weights_match_the_reference_renderer_per_gaussian():
    params, cam = sf.random_scene(seed=3, n=24, sh_degree=0, width=40, height=32)
    opaque, cam2 = sf.opaque_stack(seed=1, n=8)             # (weights near 0 behind opaque ones)
    g = mig.Gaussians.from_numpy(**params)
    got = np.array(max_weights(g, [cam])) * cam.width * cam.height
    want = np.zeros(len(got))
    for k in range(len(got)):
        want[k] = render_reference(dict(params, sh_dc=alone(len(got), k)), cam, sh_degree=0)["rgb"].sum() / 3
    assert want.max() > 1.0                                    # (more than a pixel's worth: a real test)
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-3)
    go = mig.Gaussians.from_numpy(**opaque)
    got = np.array(max_weights(go, [cam2])) * cam2.width * cam2.height
    want = [render_reference(dict(opaque, sh_dc=alone(go.n, k)), cam2, sh_degree=0)["rgb"].sum() / 3
            for k in range(go.n)]
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-3)
    assert min(want) < 1e-2 * max(want)                        # (the stack does hide some)
    # the same scene at twice the size: the same shares (a rule in pixels would differ by 4x) for the Gaussians
    # larger than a few pixels (the renderer's low-pass filter widens each by a fixed part of a pixel)
    big = sf.random_scene(seed=3, n=24, sh_degree=0, width=80, height=64, fx=2 * cam.fx, fy=2 * cam.fy)[1]
    small_share, big_share = np.array(max_weights(g, [cam])), np.array(max_weights(g, [big]))
    large = small_share > 0.01
    assert large.sum() >= 5
    np.testing.assert_allclose(big_share[large], small_share[large], rtol=0.05)
    # over several cameras: the largest per Gaussian
    both = np.array(max_weights(g, [cam, cam2]))
    np.testing.assert_allclose(both, np.maximum(np.array(max_weights(g, [cam])), np.array(max_weights(g, [cam2]))),
                               rtol=1e-6, atol=1e-6)


def test_weight_prune_removes_what_no_view_shows_at_the_end_of_densification():
    import dataclasses

    from mi_gaussians.config import DensifyConfig, OptimConfig, TrainConfig
    from mi_gaussians.optim.adam import GaussianAdam
    from mi_gaussians.optim.strategies import make_strategy

    params, cam = sf.opaque_stack(seed=1, n=8)
    g = mig.Gaussians.from_numpy(**params)
    weights = np.array(max_weights(g, [cam]))
    thr = 8.0 / (cam.width * cam.height)                       # (8 pixels' worth)
    assert 0 < (weights < thr).sum() < g.n                     # (some hidden, some shown)
    cfg = dataclasses.replace(TrainConfig(), densify=dataclasses.replace(DensifyConfig(), densify_until_iter=100,
                                                                         weight_prune=thr))
    strategy = make_strategy(cfg, 1.0, white_background=False, train_cameras=[cam])
    opt = GaussianAdam(g, OptimConfig(), 1.0)
    state = strategy.initialize_state(opt.n)
    assert strategy.refines_at(100) and not strategy.refines_at(101)
    assert strategy.refine(opt, state, 99).pruned == 0 and opt.n == g.n     # (not before)
    info = strategy.refine(opt, state, 100)
    assert info.pruned == int((weights < thr).sum()) and opt.n == g.n - info.pruned and state.n == opt.n
    np.testing.assert_array_equal(opt.gaussians.numpy()["means"], params["means"][weights >= thr])
    off = make_strategy(TrainConfig(), 1.0, white_background=False)
    assert not off.refines_at(TrainConfig().densify.densify_until_iter)     # (0: the reference, nothing)


def test_prune_unseen_removes_what_shows_less_than_the_renderers_cut_off_of_a_pixel_in_every_view():
    import dataclasses

    from mi_gaussians.config import DensifyConfig, RasterConfig, TrainConfig
    from mi_gaussians.optim.adam import GaussianAdam
    from mi_gaussians.optim.strategies import make_strategy

    params, cam = sf.opaque_stack(seed=2, n=24)                # (hidden ones behind the opaque front, some just seen)
    other, cam2 = sf.random_scene(seed=3, n=24, sh_degree=0, width=40, height=32)
    g = mig.Gaussians.from_numpy(**params)
    pixels = np.array(max_weights(g, [cam], unit="pixels"))
    np.testing.assert_allclose(pixels, np.array(max_weights(g, [cam])) * cam.width * cam.height, rtol=1e-5)
    cut = RasterConfig().alpha_min
    unseen = pixels < cut
    assert 3 <= unseen.sum() < g.n and (pixels[~unseen] < 1.5 * cut).any()    # (some just above the cut-off)
    dens = dataclasses.replace(DensifyConfig(), densify_until_iter=100, prune_unseen=True)
    cfg = dataclasses.replace(TrainConfig(), densify=dens)
    strategy = make_strategy(cfg, 1.0, white_background=False, train_cameras=[cam])
    assert strategy.unseen_weight == cut                       # (the renderer's own cut-off: one home)
    opt = GaussianAdam(g, cfg.optim, 1.0)
    state = strategy.initialize_state(opt.n)
    assert strategy.refines_at(100) and not strategy.refines_at(101)
    info = strategy.refine(opt, state, 100)
    assert info.pruned == int(unseen.sum()) and opt.n == g.n - info.pruned and state.n == opt.n
    np.testing.assert_array_equal(opt.gaussians.numpy()["means"], params["means"][~unseen])
    # a Gaussian seen in any one training view stays: the same model over a second camera that sees all of them
    seen_elsewhere = np.array(max_weights(g, [cam2], unit="pixels")) >= cut
    assert (unseen & seen_elsewhere).any()
    both = make_strategy(cfg, 1.0, white_background=False, train_cameras=[cam, cam2])
    opt2 = GaussianAdam(g, cfg.optim, 1.0)
    assert both.refine(opt2, both.initialize_state(opt2.n), 100).pruned == int((unseen & ~seen_elsewhere).sum())
    # with weight_prune as well: both rules
    thr = 8.0 / (cam.width * cam.height)
    shares = pixels / (cam.width * cam.height)
    cfg3 = dataclasses.replace(cfg, densify=dataclasses.replace(dens, weight_prune=thr))
    s3 = make_strategy(cfg3, 1.0, white_background=False, train_cameras=[cam])
    opt3 = GaussianAdam(g, cfg.optim, 1.0)
    assert s3.refine(opt3, s3.initialize_state(opt3.n), 100).pruned == int(((shares < thr) | unseen).sum())
    off = make_strategy(TrainConfig(), 1.0, white_background=False)
    assert not off.refines_at(TrainConfig().densify.densify_until_iter)     # (off: the reference keeps them)


def _separated_threshold(normalized: np.ndarray, near: float) -> float:
    """A threshold near ``near`` in the widest gap of the normalized errors (so that float32 and float64 agree on
    every pixel's side of it)."""
    v = np.sort(normalized.ravel())
    lo = np.searchsorted(v, near - 0.15)
    hi = np.searchsorted(v, near + 0.15)
    gaps = np.diff(v[lo:hi + 1])
    k = int(np.argmax(gaps))
    return float(0.5 * (v[lo + k] + v[lo + k + 1]))


def test_error_weights_match_the_reference_renderer_per_gaussian():
    """``error_weights``: per Gaussian, its blending weight in each view's high-error pixels, as a share of the
    view's pixels, averaged over the views; against the float64 reference renderer (each Gaussian alone coloured)."""
    import mitsuba as mi

    from mi_gaussians.optim.weights import error_weights

    params, cam = sf.random_scene(seed=3, n=24, sh_degree=0, width=40, height=32)
    other, _ = sf.random_scene(seed=8, n=24, sh_degree=0, width=40, height=32)
    opaque, cam2 = sf.opaque_stack(seed=1, n=8)
    g = mig.Gaussians.from_numpy(**params)
    n = g.n
    alone_images = [render_reference(dict(params, sh_dc=alone(n, k)), cam, sh_degree=0)["rgb"].sum(-1) / 3
                    for k in range(n)]
    views, want = [], np.zeros(n)
    # two views: the same camera against two targets (another scene's render; a uniform grey)
    img = render_reference(params, cam, sh_degree=0)["rgb"]
    for target in (render_reference(other, cam, sh_degree=0)["rgb"], np.full_like(img, 0.4)):
        e = np.abs(img - target).mean(-1)
        normalized = (e - e.min()) / (e.max() - e.min())
        thr = _separated_threshold(normalized, 0.3)
        mask = normalized > thr
        assert 0.05 < mask.mean() < 0.95                           # (a real mask)
        want += np.array([(a * mask).sum() for a in alone_images]) / (cam.width * cam.height)
        views.append((cam, mi.TensorXf(target.astype(np.float32)), thr))
    want /= 2
    got = sum(np.array(error_weights(g, [(c, t)], 0, (0.0, 0.0, 0.0), thr)) for c, t, thr in views) / 2
    assert want.max() * cam.width * cam.height > 1.0               # (more than a pixel's worth: a real test)
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-3 / (cam.width * cam.height))
    # the mean over several views in one call
    same = np.array(error_weights(g, [(c, t) for c, t, _ in views[:1]] * 2, 0, (0.0, 0.0, 0.0), views[0][2]))
    np.testing.assert_allclose(same, np.array(error_weights(g, [views[0][:2]], 0, (0.0, 0.0, 0.0), views[0][2])),
                               rtol=1e-6, atol=1e-12)
    # Gaussians hidden behind opaque ones weigh (almost) nothing, whatever the error behind them
    go = mig.Gaussians.from_numpy(**opaque)
    shown = np.array(max_weights(go, [cam2]))
    err = np.array(error_weights(go, [(cam2, mi.TensorXf(np.full((cam2.height, cam2.width, 3), 0.4, np.float32)))],
                                 0, (0.0, 0.0, 0.0), 0.0))
    assert np.all(err <= shown + 1e-7) and err.max() > 0


def test_the_error_gate_scores_the_training_views_it_is_given():
    """``make_strategy`` with ``densify.error_gate`` scores the model on ``densify.error_views`` of the training views
    (all of them when there are fewer: their mean), the same views for the same iteration; without training views it
    is refused."""
    import dataclasses

    import mitsuba as mi
    import pytest

    from mi_gaussians.config import DensifyConfig, TrainConfig
    from mi_gaussians.optim.strategies import make_strategy
    from mi_gaussians.optim.weights import error_weights

    params, cam = sf.random_scene(seed=3, n=24, sh_degree=1, width=40, height=32)
    other, _ = sf.random_scene(seed=8, n=24, sh_degree=1, width=40, height=32)
    g = mig.Gaussians.from_numpy(**params)
    targets = [mi.TensorXf(render_reference(other, cam, sh_degree=1)["rgb"].astype(np.float32)),
               mi.TensorXf(np.full((cam.height, cam.width, 3), 0.4, np.float32)),
               mi.TensorXf(np.full((cam.height, cam.width, 3), 0.9, np.float32))]

    class Views:
        def __len__(self):
            return len(targets)

        def camera(self, i):
            return cam

        def target(self, i):
            return targets[i]

    def strategy(views_drawn):
        cfg = dataclasses.replace(TrainConfig(), densify=dataclasses.replace(
            DensifyConfig(), error_gate=1e-4, error_views=views_drawn, error_threshold=0.2))
        return make_strategy(cfg, 1.0, white_background=False, training_views=Views(), background=(0.2, 0.2, 0.2))

    everything = np.array(strategy(5).view_errors(g, 3000))            # (degree 1 from iteration 1000 on)
    want = np.array(error_weights(g, [(cam, t) for t in targets], 1, (0.2, 0.2, 0.2), 0.2))
    np.testing.assert_allclose(everything, want, rtol=1e-5, atol=1e-10)
    assert np.array(error_weights(g, [(cam, t) for t in targets], 0, (0.2, 0.2, 0.2), 0.2)).tolist() != want.tolist()
    one = strategy(1)
    singles = [np.array(error_weights(g, [(cam, t)], 1, (0.2, 0.2, 0.2), 0.2)) for t in targets]
    drawn = [np.array(one.view_errors(g, step)) for step in range(1100, 1400, 100)]
    for d in drawn:                                                    # one view each time, one of the three
        assert any(np.allclose(d, s, rtol=1e-5, atol=1e-10) for s in singles)
    np.testing.assert_array_equal(np.array(one.view_errors(g, 1200)), drawn[1])
    with pytest.raises(ValueError, match="training views"):
        make_strategy(dataclasses.replace(TrainConfig(), densify=dataclasses.replace(DensifyConfig(), error_gate=1e-4)),
                      1.0, white_background=False)
