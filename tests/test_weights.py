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
