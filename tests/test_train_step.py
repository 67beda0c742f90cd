"""The frozen training step (mi_gaussians.optim.train_step) and the loop around it: fixed-capacity binning equals the
exact binning, a masked Adam step is no step, frozen training gives the model traced training gives (bit for bit on
one thread, densification and instance-capacity overflows included), and replays compile and record nothing new.
Every test runs on the variant of ``pytest --variant``."""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from kernel_log import KernelLog
from mi_gaussians.optim.adam import GaussianAdam
from test_adam import EXTENT, loss_and_backward, make_gaussians
from test_train import load, scene, small_config  # noqa: F401  (scene is a fixture)


#: Why runs are not compared bit for bit on CUDA (the ``one_thread`` fixture skips there).
CUDA_ATOMICS = ("CUDA's float atomics (the backward pass's scatter-adds) sum in an order that changes from run to run: "
                "two runs differ by an ulp from their second iteration (seen on an H100: loss 0.4279884696 against "
                "0.4279884994 at iteration 3, frozen and traced loops alike); bit-for-bit comparisons hold on LLVM "
                "with one thread, and test_frozen_training_tracks_traced_training checks CUDA within float noise")


@pytest.fixture
def one_thread(ordered_sums):
    """Dr.Jit on one thread (conftest's ``ordered_sums``): the order of atomic additions, hence every bit of a run,
    is then reproducible. CUDA has no such switch: tests that need it are skipped there (:data:`CUDA_ATOMICS`)."""
    if dr.backend_v(mi.Float) == dr.JitBackend.CUDA:
        pytest.skip(CUDA_ATOMICS)


def test_capacity_binning_equals_exact_binning():
    from mi_gaussians.raster.binning import bin_gaussians

    rng = np.random.default_rng(3)
    n, tiles_x, tiles_y = 400, 7, 5
    x0, y0 = rng.integers(0, tiles_x, n), rng.integers(0, tiles_y, n)
    x1 = np.minimum(x0 + rng.integers(0, 3, n), tiles_x - 1)
    y1 = np.minimum(y0 + rng.integers(0, 3, n), tiles_y - 1)
    culled = rng.random(n) < 0.2
    count = np.where(culled, 0, (x1 - x0 + 1) * (y1 - y0 + 1)).astype(np.uint32)
    depth = mi.Float(np.round(rng.uniform(1, 5, n), 1).astype(np.float32))    # many equal depths: stability
    rect = tuple(mi.Int32(a.astype(np.int32)) for a in (x0, y0, x1, y1))
    total = int(count.sum())

    exact = bin_gaussians(depth, rect, mi.UInt32(count), tiles_x, tiles_y)
    assert exact.n_instances == total
    for capacity in (total, total + 1, 3 * total):
        b = bin_gaussians(depth, rect, mi.UInt32(count), tiles_x, tiles_y, capacity=capacity)
        assert bool(b.fits[0]) and int(b.n_instances[0]) == total
        np.testing.assert_array_equal(np.array(b.tile_start), np.array(exact.tile_start))
        np.testing.assert_array_equal(np.array(b.gaussian)[:total], np.array(exact.gaussian))
    short = bin_gaussians(depth, rect, mi.UInt32(count), tiles_x, tiles_y, capacity=total - 1)
    assert not bool(short.fits[0]) and int(short.n_instances[0]) == total


def test_masked_adam_step_is_no_step():
    """``step(active=False)`` changes no value, moment or step count (Dr.Jit's own mask lets t count on);
    ``step(active=True)`` is ``step()``."""
    from mi_gaussians.config import OptimConfig

    a = GaussianAdam(make_gaussians(), OptimConfig(), EXTENT)
    b = GaussianAdam(make_gaussians(), OptimConfig(), EXTENT)
    for p in (a, b):
        loss_and_backward(p.gaussians)
        p.step()
        loss_and_backward(p.gaussians, salt=1)
    before = {k: a.moments(k) for k in a.keys()}
    values = a.gaussians.numpy()
    a.step(active=dr.opaque(mi.Bool, False))
    for k in a.keys():
        t, m, v = a.moments(k)
        assert t == before[k][0] == 1
        np.testing.assert_array_equal(m, before[k][1])
        np.testing.assert_array_equal(v, before[k][2])
        np.testing.assert_array_equal(a.gaussians.numpy()[k], values[k])
    loss_and_backward(a.gaussians, salt=1)
    a.step(active=dr.opaque(mi.Bool, True))
    b.step()
    for k in a.keys():
        np.testing.assert_array_equal(a.gaussians.numpy()[k], b.gaussians.numpy()[k], err_msg=k)
        assert a.moments(k)[0] == b.moments(k)[0] == 2


def _train(scene, cfg, steps, capacity=None):  # noqa: F811
    return _train_ds(load(scene, cfg), cfg, steps, capacity)


def _train_ds(ds, cfg, steps, capacity=None):
    """``steps`` iterations of a Trainer on the dataset ``ds`` (frozen steps resolved), optionally with a fixed
    instance capacity after every traced iteration."""
    from mi_gaussians.optim.trainer import Trainer

    import tempfile

    tr = Trainer(ds, cfg, tempfile.mkdtemp(), progress=False)
    if capacity is not None:
        def tiny(instances):
            tr.capacity, tr._peak = capacity, 0
        tr._set_capacity_after_traced = tiny
    while tr.step < steps or tr._pending:
        if tr.step < steps:
            tr.advance()
        else:
            tr._resolve()
    tr.trim()               # (a frozen loop ends on its model padded to a size class)
    return tr


@pytest.mark.parametrize("capacity", [None, 512])
def test_frozen_training_equals_traced_training(scene, one_thread, capacity):  # noqa: F811
    """130 iterations with densifications at 100 and 150... (the config's), an opacity reset, SH degree rising at 100:
    the frozen loop ends with the traced loop's model, moments, statistics and losses, bit for bit. With a capacity of
    512 instances after every traced iteration, frozen steps overflow, are masked and replayed with a larger one."""
    steps = 130
    cfg = small_config(300)
    frozen = _train(scene, cfg, steps, capacity)
    traced = _train(scene, dataclasses.replace(cfg, freeze=False), steps)
    assert frozen.train_step.recordings >= 1 and traced.train_step.recordings == 0
    assert (frozen.loop.overflows > 0) == (capacity is not None)
    assert frozen.step == traced.step == steps
    assert frozen.history.iteration == list(range(1, steps + 1))
    assert_same_training(frozen, traced)


def test_frozen_training_tracks_traced_training(scene):  # noqa: F811
    """Frozen and traced loops over 60 iterations before any densification, on every thread the backend has: the same
    losses and model within float noise. The bit-for-bit tests above need ordered float sums (LLVM on one thread);
    this one holds wherever atomics reorder them (CUDA, several LLVM threads)."""
    cfg = small_config(300)
    frozen = _train(scene, cfg, 60)
    traced = _train(scene, dataclasses.replace(cfg, freeze=False), 60)
    assert frozen.train_step.recordings >= 1 and frozen.params.n == traced.params.n
    np.testing.assert_allclose(frozen.history.loss, traced.history.loss, rtol=1e-3)
    # parameters that get almost no gradient can move differently (Adam divides the noise by its own size): compare
    # what the models draw (on 2 LLVM threads: identical, or ~1e-6 apart at most)
    from mi_gaussians.metrics import psnr
    from mi_gaussians.raster.rasterize import render

    for v in frozen.ds.train[:3]:
        a, b = (np.array(render(t.gaussians, v.camera).rgb) for t in (frozen, traced))
        assert psnr(a, b) > 60.0


def test_frozen_training_with_the_cuda_sorts_equals_traced_training(scene, one_thread, monkeypatch):  # noqa: F811
    """The binning's CUDA sorts (8-bit digit passes, padded while a frozen function records them: Dr.Jit 1.5.0 crashes
    replaying an unpadded one on CUDA) run on this backend: the frozen loop, which records and replays them, ends with
    the traced loop's model, bit for bit."""
    from mi_gaussians.raster import binning

    monkeypatch.setattr(binning, "_is_cuda", lambda values: True)
    cfg = small_config(300)
    frozen = _train(scene, cfg, 120, 512)
    traced = _train(scene, dataclasses.replace(cfg, freeze=False), 120)
    assert frozen.train_step.recordings >= 1 and frozen.loop.overflows > 0
    assert_same_training(frozen, traced)


def test_the_chosen_lane_layout_reaches_frozen_and_traced_steps(scene, one_thread, monkeypatch):  # noqa: F811
    """``raster.lanes`` 'balanced': the layout ``balanced_layout`` gives at the first iteration and at each refinement
    is the one the iterations after it blend with. Choices alternating between two CPU layouts: the frozen steps
    report the traced renders' heaviest-tile shares (the same values at the same choices), the frozen loop ends with
    the traced loop's model bit for bit and counts each layout's iterations; 'fixed' asks for no choice."""
    from mi_gaussians.optim import trainer as trainer_module
    from mi_gaussians.raster.blend import LANE_LAYOUTS, LaneLayout

    other = LaneLayout(pixels=4, start_lanes=8, tile_rows=8, tile_cols=8)
    calls = []

    def alternate(share, cuda, radius=None):
        calls[-1].append((share, radius))
        return other if len(calls[-1]) % 2 else LANE_LAYOUTS["llvm"]

    monkeypatch.setattr(trainer_module, "balanced_layout", alternate)
    cfg = small_config(300)
    runs = []
    for c in (cfg, dataclasses.replace(cfg, freeze=False)):
        calls.append([])
        runs.append(_train(scene, c, 130))
    frozen, traced = runs
    assert len(calls[0]) >= 2 and calls[0] == calls[1] and all(0 < s <= 1 and r > 0 for s, r in calls[0])
    assert frozen.loop.lanes == traced.loop.lanes
    assert set(frozen.loop.lanes) == {other.label, LANE_LAYOUTS["llvm"].label}
    assert sum(frozen.loop.lanes.values()) == 130
    assert_same_training(frozen, traced)
    calls.append([])
    fixed = _train(scene, dataclasses.replace(cfg, raster=dataclasses.replace(cfg.raster, lanes="fixed")), 130)
    assert calls[-1] == [] and fixed.layout is None and fixed.loop.lanes == {LANE_LAYOUTS["llvm"].label: 130}
    # (the two layouts sum the gradients in another order: the model is not the same bits, so the frozen loop's
    # equality with the traced one above says both blended with the chosen layouts)
    assert any(not np.array_equal(frozen.gaussians.numpy()[k], v) for k, v in fixed.gaussians.numpy().items())


def test_frozen_absgrad_training_equals_traced_training(scene, one_thread):  # noqa: F811
    """With --absgrad, densifying at 100 and until 110 of 130 iterations: the frozen steps that gather statistics
    ask the backward pass for the absolute sums and those after 110 do not, and the run ends with the traced loop's
    model, bit for bit."""
    cfg = small_config(300)
    cfg = dataclasses.replace(cfg, densify=dataclasses.replace(cfg.densify, absgrad=True, densify_from_iter=50,
                                                               densify_until_iter=110,
                                                               absgrad_threshold=1e-4))
    frozen = _train(scene, cfg, 130)
    traced = _train(scene, dataclasses.replace(cfg, freeze=False), 130)
    assert frozen.params.n != cfg.data.random_points          # (densification did happen)
    assert_same_training(frozen, traced)


def assert_same_training(a, b) -> None:
    """Two trainers ended with the same model, moments, strategy state, losses and view order, bit for bit."""
    assert a.params.n == b.params.n and a.history.loss == b.history.loss
    for k, v in b.gaussians.numpy().items():
        np.testing.assert_array_equal(a.gaussians.numpy()[k], v, err_msg=k)
    ma, mb = a.params.export_moments(), b.params.export_moments()
    assert ma.keys() == mb.keys()
    for k in mb:
        np.testing.assert_array_equal(ma[k], mb[k], err_msg=k)
    (sa, meta_a), (sb, meta_b) = (x.strategy.export_state(x.strategy_state) for x in (a, b))
    assert sa.keys() == sb.keys() and meta_a == meta_b
    for k in sb:
        np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)
    assert a.sampler.state() == b.sampler.state()


def stopped_and_resumed(data, cfg, tmp_path, stop: int = 60):
    """(resumed, whole): a run of ``cfg`` on ``data`` stopped at iteration ``stop`` and resumed from its checkpoint to
    the end, and the same run never stopped; the caller compares them (:func:`assert_same_training`)."""
    from mi_gaussians.optim.trainer import Trainer

    first = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, iterations=stop))
    Trainer(load(data, first), first, tmp_path / "run", progress=False).run()
    resumed = Trainer(load(data, cfg), cfg, tmp_path / "run", progress=False)
    resumed.run(resume=True)
    whole = Trainer(load(data, cfg), cfg, tmp_path / "whole", progress=False)
    whole.run()
    assert resumed.resumed_from == stop
    return resumed, whole


def test_replays_record_and_compile_nothing_new(scene):  # noqa: F811
    """Without densification, after a warm-up every training view (other cameras, targets, random backgrounds,
    instance counts) replays the same recording and launches no kernel that is not compiled yet."""
    cfg = small_config(1000)
    cfg = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, sh_increase_interval=10_000,
                                                             random_background=True),
                              densify=dataclasses.replace(cfg.densify, densify_from_iter=10_000,
                                                          densify_until_iter=10_000))
    with KernelLog() as log:      # (JIT flags are part of a recording's key: the history flag is on from the start)
        tr = _train(scene, cfg, 6)
        recordings = tr.train_step.recordings
        assert 1 <= recordings <= 3
        syncs = tr.loop.syncs       # (the warm-up's: its traced iterations, and on the CPU a new tile grid's)
        log.cut()
        for _ in range(2 * len(tr.ds.train)):
            tr.advance()
        tr._resolve()
        log.cut()
    assert tr.train_step.recordings == recordings
    assert tr.loop.syncs - syncs < 2 * len(tr.ds.train) / 5
    assert len(log.windows[1]) > 20
    unseen = log.unseen(1)
    assert not unseen, f"{len(unseen)} of {len(log.windows[1])} kernels not launched in the warm-up: {unseen[:5]}"


def test_the_model_of_a_refinement_iteration_is_scored_before_its_refinement(scene, tmp_path, one_thread):  # noqa: F811
    """A run that ends on a refinement iteration (150: densification and opacity reset) scores and saves the model of
    that iteration before the refinement, as the reference's train.py: no unoptimized clones, no opacities just reset
    to 0.01. Its checkpoint records the refinement as pending; resumed to 200 iterations, the run applies it first and
    ends as an uninterrupted 200-iteration run does."""
    import json

    import mi_gaussians as mig
    from mi_gaussians.optim.trainer import Trainer

    def config(iterations):
        cfg = small_config(400)
        return dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, iterations=iterations),
                                   densify=dataclasses.replace(cfg.densify, densify_until_iter=200))

    short = Trainer(load(scene, config(150)), config(150), tmp_path / "short", progress=False)
    assert short.strategy.refines_at(150)
    metrics = short.run()
    g = mig.Gaussians.load_ply(tmp_path / "short" / "point_cloud.ply")
    history = json.loads((tmp_path / "short" / "history.json").read_text())
    assert metrics["gaussians"] == g.n == history["gaussians"][-1] == history["gaussians"][-2]   # no clone added
    assert np.max(1 / (1 + np.exp(-np.asarray(g.numpy()["opacities"], np.float64)))) > 0.05      # not reset
    with np.load(tmp_path / "short" / "checkpoints" / "ckpt.npz") as z:
        assert json.loads(bytes(z["meta"]).decode())["refine_pending"] == 150
    resumed = Trainer(load(scene, config(200)), config(200), tmp_path / "short", progress=False)
    resumed.run(resume=True)
    straight = Trainer(load(scene, config(200)), config(200), tmp_path / "straight", progress=False)
    straight.run()
    assert resumed.params.n == straight.params.n != g.n
    for k, v in straight.gaussians.numpy().items():
        np.testing.assert_allclose(resumed.gaussians.numpy()[k], v, rtol=1e-4, atol=1e-6, err_msg=k)


def test_size_classes_train_the_unpadded_model_with_fewer_recordings(scene, one_thread):  # noqa: F811
    """Frozen steps on the model padded with inert rows to its size class (``row_classes=2``) end with the model
    that frozen steps at its own size (``row_classes=0``, the default) train, bit for bit, through densifications that
    change the number of Gaussians (within a class and across classes); the padded run records once per class and
    capacity, the other once per size. (Two classes per doubling: with four, on this small model, the instance
    capacities' own changes on the CPU's tiles left the two runs with as many recordings.)"""
    from mi_gaussians.optim.train_step import row_class

    cfg = small_config(200)
    # (one tile grid: the CPU's smaller tiles for small Gaussians bring more capacity changes, each a recording,
    # which on this small model can leave the two runs with as many)
    cfg = dataclasses.replace(cfg, densify=dataclasses.replace(cfg.densify, densify_from_iter=20,
                                                               densify_until_iter=180, densification_interval=20,
                                                               grad_threshold=4e-4),
                              raster=dataclasses.replace(cfg.raster, lanes="fixed"))
    padded = _train(scene, dataclasses.replace(cfg, row_classes=2), 200)
    own = _train(scene, dataclasses.replace(cfg, row_classes=0), 200)
    assert_same_training(padded, own)
    sizes = sorted(set(own.history.gaussians))
    classes = {row_class(n, 2) for n in sizes}
    assert len(sizes) >= 4 and 2 <= len(classes) < len(sizes)
    assert padded.loop.recordings < own.loop.recordings


@pytest.mark.parametrize("antialiased", [False, True])
def test_inert_rows_change_no_render_and_get_no_gradient(antialiased, one_thread):
    """Rows from ``inert_rows`` appended to a model: the render (colour, alpha, depth) and every gradient of the
    model's own rows are bit-identical to the model's alone (on one thread: the gradients are scatter-added); the
    inert rows get radius 0 and zero gradients, and an Adam step leaves them exactly in place (zero moments)."""
    from mi_gaussians.config import OptimConfig, RasterConfig
    from mi_gaussians.model.gaussians import Gaussians
    from mi_gaussians.optim.train_step import inert_rows
    from mi_gaussians.raster.rasterize import render
    from raster_helpers import random_weights, weighted_loss
    from scene_factory import random_scene

    params_np, cam = random_scene(seed=5, n=60, sh_degree=2)
    raster = RasterConfig(antialiased=antialiased)
    results = []
    for pad in (0, 37):
        p = GaussianAdam(Gaussians.from_numpy(**params_np), OptimConfig(), 1.0)
        if pad:
            p.append(inert_rows(p, pad))
            inert = {k: np.array(p[k].array) for k in p.keys()}
        out = render(p.gaussians, cam, cfg=raster)
        dr.backward(weighted_loss(out, random_weights(cam, seed=2)))
        grads = {k: np.array(dr.grad(p[k]).array).reshape(p[k].shape) for k in p.keys()}
        image = {a: np.array(getattr(out, a).array) for a in ("rgb", "alpha", "depth")}
        radii = np.array(out.radii)
        p.step()
        results.append((image, grads, radii, p))
    (image0, grads0, radii0, _), (image1, grads1, radii1, p1) = results
    n = len(radii0)
    for a in image0:
        np.testing.assert_array_equal(image1[a], image0[a], err_msg=a)
    np.testing.assert_array_equal(radii1[:n], radii0)
    assert not radii1[n:].any() and radii0.any()
    for k in grads0:
        np.testing.assert_array_equal(grads1[k][:n], grads0[k], err_msg=k)
        assert not grads1[k][n:].any(), k
        after = np.array(p1[k].array).reshape(p1[k].shape)[n:]
        np.testing.assert_array_equal(after.reshape(-1), inert[k].reshape(p1[k].shape)[n:].reshape(-1), err_msg=k)


def test_row_classes_are_a_geometric_ladder():
    """``row_class`` with 4 classes per doubling: at least the rows asked for, a multiple of 256, at most one rung
    (2^(1/4)) plus rounding above, the same class for every size of a rung; with 0, the size itself."""
    from mi_gaussians.optim.train_step import row_class

    sizes = np.unique(np.geomspace(1, 3e6, 4000).astype(int))
    classes = np.array([row_class(int(n), 4) for n in sizes])
    assert (classes >= sizes).all() and (classes % 256 == 0).all()
    assert (classes <= np.maximum(1024, sizes * 2 ** 0.25 + 256)).all()
    assert (np.diff(classes) >= 0).all()
    assert len(np.unique(classes)) < len(sizes) / 50
    assert [row_class(n, 0) for n in (1, 1000, 12345)] == [1, 1000, 12345]
    assert row_class(5000, 2) >= row_class(5000, 4)


def test_a_padded_run_checkpoints_its_own_rows_and_resumes_as_it_runs(scene, tmp_path, one_thread):  # noqa: F811
    """A run on frozen steps padded to size classes, stopped between two densifications and resumed, ends as the run
    never stopped does, bit for bit; its checkpoint holds the model's own rows, no inert one."""
    cfg = small_config(160)
    cfg = dataclasses.replace(cfg, row_classes=4, checkpoint_every=1000,
                              densify=dataclasses.replace(cfg.densify, densify_from_iter=20, densify_until_iter=140,
                                                          densification_interval=20, grad_threshold=4e-4))
    resumed, whole = stopped_and_resumed(scene, cfg, tmp_path, stop=90)
    from mi_gaussians.optim.train_step import row_class

    assert_same_training(resumed, whole)
    with np.load(tmp_path / "run" / "checkpoints" / "ckpt.npz") as z:      # (the resumed run's, at its end)
        n = len(z["param/opacities"])
    assert n == resumed.params.n == resumed.history.gaussians[-1] != row_class(n, 4)
