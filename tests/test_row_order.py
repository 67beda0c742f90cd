"""The model's rows sorted by where the Gaussians are (mi_gaussians.optim.row_order, ``optim.row_order``): the order
is a stable sort of Morton codes that keeps neighbours together, the parameters, their Adam moments and the
strategy's statistics move together, a sorted model renders the same images with the same (permuted) gradients, and a
run keeps its rows sorted from the start and after each densification ('creation' leaves the reference's order)."""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
import scene_factory as sf
from mi_gaussians.config import DensifyConfig, OptimConfig
from mi_gaussians.model.gaussians import PARAMETER_NAMES
from mi_gaussians.optim.adam import GaussianAdam
from mi_gaussians.optim.densify import DefaultStrategy
from mi_gaussians.optim.row_order import BITS, morton_codes, order_rows, spatial_order


def _codes(means: np.ndarray) -> np.ndarray:
    return np.array(morton_codes(mi.Float(np.ascontiguousarray(means, np.float32).ravel())), np.int64)


def _order(means: np.ndarray) -> np.ndarray:
    return np.array(spatial_order(mi.Float(np.ascontiguousarray(means, np.float32).ravel())), np.int64)


def test_the_order_is_a_stable_sort_of_the_morton_codes():
    rng = np.random.default_rng(0)
    means = rng.normal(size=(2000, 3)).astype(np.float32)
    means[:20] *= 1e4                                     # floaters far away: the border cells
    means[20:40] = means[40:60]                           # equal means: equal codes
    means[60, 1], means[61, 2] = np.nan, np.inf           # non-finite: cell 0 on that axis, no crash
    order, codes = _order(means), _codes(means)
    assert sorted(order) == list(range(len(means)))
    np.testing.assert_array_equal(order, np.argsort(codes, kind="stable"))
    assert (np.diff(codes[order]) >= 0).all()
    assert codes.max() < 1 << (3 * BITS)
    # the floaters do not squeeze the rest into a few cells
    assert len(np.unique(codes[100:])) > 0.9 * (len(means) - 100)
    for n in (0, 1):
        assert list(_order(means[:n])) == list(range(n))
    assert list(_order(np.ones((5, 3)))) == list(range(5))      # one point: every code equal, the order kept


def test_the_codes_interleave_the_axes_and_keep_neighbours_together():
    # the corners of a cube: the axes' bits interleaved, x lowest
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], np.float32)
    codes = _codes(corners)
    assert list(np.argsort(codes)) == list(range(8)) and len(set(codes)) == 8
    # two clusters far apart, interleaved in the rows: each ends up in one contiguous run
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(500, 3)) * 0.01, rng.normal(size=(500, 3)) * 0.01 + 1.0
    means = np.empty((1000, 3), np.float32)
    means[0::2], means[1::2] = a, b
    cluster = (np.arange(1000) % 2)[_order(means)]
    assert np.count_nonzero(np.diff(cluster)) == 1


def _model(seed=3):
    params, cam = sf.random_scene(seed=seed, n=300, sh_degree=2, width=53, height=37)
    return params, cam


def test_order_rows_moves_values_moments_and_statistics_together():
    params, cam = _model()
    opt = GaussianAdam(mig.Gaussians.from_numpy(**params), OptimConfig(), extent=2.0)
    strategy = DefaultStrategy(DensifyConfig(), extent=2.0)
    state = strategy.initialize_state(opt.n)
    out = mig.render(opt.gaussians, cam)
    dr.backward(dr.sum(out.rgb.array))
    strategy.update_state(state, out)
    opt.step()                                            # moments of every row
    before = {k: opt[k].numpy().copy() for k in opt.keys()}
    moments = {k: opt.moments(k) for k in opt.keys()}
    stats, _ = strategy.export_state(state)
    assert stats["denom"].max() > 0
    perm = np.array(order_rows(opt, strategy, state), np.int64)
    assert sorted(perm) == list(range(opt.n)) and (perm != np.arange(opt.n)).any()
    np.testing.assert_array_equal(perm, _order(before["means"]))
    for k in opt.keys():
        np.testing.assert_array_equal(opt[k].numpy(), before[k][perm], err_msg=k)
        t, m, v = opt.moments(k)
        assert t == moments[k][0]
        np.testing.assert_array_equal(m, moments[k][1][perm], err_msg=k)
        np.testing.assert_array_equal(v, moments[k][2][perm], err_msg=k)
    after, _ = strategy.export_state(state)
    for k, v in stats.items():
        np.testing.assert_array_equal(after[k], v[perm], err_msg=k)


def test_a_sorted_model_renders_the_same_with_its_gradients_in_its_rows():
    params, cam = _model(seed=4)
    perm = _order(params["means"])
    results = []
    for p in (params, {k: v[perm] for k, v in params.items()}):
        g = mig.Gaussians.from_numpy(**p)
        for k in PARAMETER_NAMES:
            dr.enable_grad(getattr(g, k))
        out = mig.render(g, cam, background=(0.2, 0.3, 0.4))
        w = mi.Float(np.random.default_rng(5).normal(size=cam.height * cam.width * 3).astype(np.float32))
        dr.backward(dr.sum(out.rgb.array * w) + dr.sum(out.alpha.array))
        results.append((np.array(out.rgb), np.array(out.alpha),
                        {k: np.array(dr.grad(getattr(g, k))).reshape(p[k].shape) for k in PARAMETER_NAMES}))
    (rgb, alpha, grads), (rgb2, alpha2, grads2) = results
    np.testing.assert_array_equal(rgb2, rgb)
    np.testing.assert_array_equal(alpha2, alpha)
    for k in PARAMETER_NAMES:
        scale = max(np.abs(grads[k]).max(), 1e-12)
        np.testing.assert_allclose(grads2[k], grads[k][perm], rtol=0, atol=1e-5 * scale, err_msg=k)


@pytest.mark.parametrize("order", ["spatial", "creation"])
def test_a_run_keeps_its_rows_sorted(tmp_path, order):
    from mi_gaussians.config import DataConfig, TrainConfig
    from mi_gaussians.optim.strategies import initial_gaussians
    from mi_gaussians.optim.trainer import Trainer
    from synthetic_dataset import make_blender_dataset

    root = make_blender_dataset(tmp_path / "scene", n_train=6, n_test=1, size=32)
    cfg = TrainConfig(data=DataConfig(background=(1.0, 1.0, 1.0), random_points=2000),
                      optim=OptimConfig(iterations=120, position_lr_max_steps=120, sh_degree=1, row_order=order),
                      densify=DensifyConfig(densify_from_iter=20, densify_until_iter=100, densification_interval=50,
                                            opacity_reset_interval=0, empty_background="off"),
                      checkpoint_every=10 ** 6, eval_every=0, save_iterations=())
    ds = mig.load_dataset(root, background=cfg.data.background, random_points=cfg.data.random_points,
                          seed=cfg.data.seed)
    tr = Trainer(ds, cfg, tmp_path / "run", progress=False)
    means = tr.gaussians.numpy()["means"]
    created = initial_gaussians(ds, cfg.optim.sh_degree, tr.strategy, seed=cfg.seed + 3).numpy()["means"]
    if order == "creation":
        np.testing.assert_array_equal(means, created)
    else:
        np.testing.assert_array_equal(means, created[_order(created)])
    n0 = tr.params.n
    while tr.step < 50:                                   # up to the densification at 50 ...
        tr.advance()
    tr._drain()
    assert tr._refine_at == 50
    tr._refine()                                          # ... which runs before iteration 51
    assert tr.params.n != n0                              # (it densified)
    codes = _codes(tr.gaussians.numpy()["means"])
    if order == "spatial":
        assert (np.diff(codes) >= 0).all()
    else:
        assert (np.diff(codes) < 0).any()


def test_row_order_is_a_setting():
    from mi_gaussians.config import TrainConfig

    assert OptimConfig().row_order == "spatial"
    cfg = TrainConfig().with_settings(["optim.row_order=creation"])
    assert cfg.optim.row_order == "creation"
    from mi_gaussians.setting_values import SettingError

    with pytest.raises(SettingError, match="optim.row_order.*not one of spatial, creation"):
        TrainConfig().with_settings(["optim.row_order=random"]).validate()
    assert dataclasses.replace(OptimConfig(), row_order="creation").row_order == "creation"


def test_sorting_another_model_compiles_nothing_new():
    """A refinement's sort of the rows: its kernels do not depend on the model's size or box (as literals they would
    be compiled anew at every refinement of a run)."""
    from kernel_log import KernelLog

    strategy = DefaultStrategy(DensifyConfig(), extent=2.0)
    models = []
    for seed, n, scale in ((6, 300, 1.0), (7, 517, 30.0)):
        params, _ = sf.random_scene(seed=seed, n=n, sh_degree=1)
        params["means"] = (params["means"] * scale).astype(np.float32)
        opt = GaussianAdam(mig.Gaussians.from_numpy(**params), OptimConfig(), extent=2.0)
        models.append((opt, strategy.initialize_state(opt.n)))
    with KernelLog() as log:
        for opt, state in models:
            order_rows(opt, strategy, state)
            dr.eval(opt["means"], state.reset_done)
            log.cut()
    assert log.windows[1] and not log.unseen(1), log.unseen(1)
