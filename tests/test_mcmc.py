"""MCMC densification (mi_gaussians.optim.mcmc): the relocation correction against a 50-digit transcription of the
paper's double sum, the relocation and growth statistics (counts, sources drawn in proportion to opacity, the
conserved opacity relation, moments of written rows reset and all other rows untouched), the budget never exceeded
in training, the position noise's covariance and gating, the regularizers' gradient, frozen training equal to
traced training, checkpoints, and the command line."""

from __future__ import annotations

import dataclasses
import json
import math
from decimal import Decimal, getcontext

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_gaussians.config import MCMCConfig, OptimConfig
from mi_gaussians.model.gaussians import Gaussians
from mi_gaussians.optim.adam import GaussianAdam
from mi_gaussians.optim.mcmc import MAX_OPACITY, MCMCStrategy, relocation
from test_adam import EXTENT, loss_and_backward
from test_train import load, scene, small_config  # noqa: F401  (scene is a fixture)
from test_train_step import _train, assert_same_training, one_thread, stopped_and_resumed  # noqa: F401  (one_thread is a fixture)


def _paper_denominator(o_new: float, n: int) -> Decimal:
    """sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1), in 50-digit decimals, as gsplat's kernel
    loops."""
    getcontext().prec = 50
    o = Decimal(o_new)
    total = Decimal(0)
    for i in range(1, n + 1):
        for k in range(i):
            total += Decimal(math.comb(i - 1, k)) * (-1) ** k * o ** (k + 1) / Decimal(k + 1).sqrt()
    return total


def test_relocation_matches_the_papers_double_sum():
    rng = np.random.default_rng(0)
    o = np.concatenate([rng.uniform(0.006, 0.999, 40), [0.5, 0.99, MAX_OPACITY, 0.006]])
    n = np.concatenate([rng.integers(1, 51, 40), [50, 50, 50, 1]])
    s = rng.uniform(0.01, 2.0, (len(o), 3))
    new_o, new_s = relocation(o, s, n)
    for i in range(len(o)):
        o_new = 1 - (1 - Decimal(o[i])) ** (Decimal(1) / Decimal(int(n[i])))
        assert abs(Decimal(new_o[i]) - o_new) <= Decimal(1e-15)
        denom = _paper_denominator(float(new_o[i]), int(n[i]))
        expect = np.array([float(Decimal(x) * Decimal(o[i]) / denom) for x in s[i]])
        np.testing.assert_allclose(new_s[i], expect, rtol=1e-11, err_msg=f"o={o[i]}, N={n[i]}")
    # N copies in a row let exactly o through
    np.testing.assert_allclose(1 - (1 - new_o) ** np.clip(n, 1, 50), o, rtol=1e-12)
    # one copy is the Gaussian itself
    one_o, one_s = relocation(o, s, np.ones(len(o), int))
    np.testing.assert_allclose(one_o, o, rtol=1e-14)
    np.testing.assert_allclose(one_s, s, rtol=1e-14)
    # more than 50 copies are corrected as 50 (gsplat's table)
    np.testing.assert_array_equal(relocation(o, s, n * 0 + 80)[1], relocation(o, s, n * 0 + 50)[1])


def _model(opacity: np.ndarray, seed=0) -> GaussianAdam:
    """A model with the given opacities and Adam moments that are nonzero everywhere."""
    n = len(opacity)
    rng = np.random.default_rng(seed)
    logit = np.log(opacity / (1 - opacity))
    g = Gaussians.from_numpy(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) - 3.0, rng.normal(size=(n, 4)),
                             logit, rng.normal(size=(n, 3)), rng.normal(size=(n, 3, 3)))
    p = GaussianAdam(g, OptimConfig(), EXTENT)
    loss_and_backward(p.gaussians)
    p.step()
    # (the step moved the opacities: put them back, keeping the moments)
    p.replace("opacities", mi.TensorXf(mi.Float(logit.astype(np.float32))))
    return p


def _snapshot(p: GaussianAdam) -> tuple[dict, dict]:
    return p.gaussians.numpy(), {k: p.moments(k)[1:] for k in p.keys()}


def _sigmoid(x):
    return 1 / (1 + np.exp(-np.asarray(x, np.float64)))


def test_relocation_statistics():
    """Dead rows become copies of live ones drawn in proportion to opacity; each source and its copies carry the
    corrected opacity (N copies let the old opacity through) and scale; written rows have zero moments, every other
    row is untouched (values and moments bit for bit)."""
    levels = np.array([0.1, 0.3, 0.9])
    n_alive, n_dead = 300, 6000
    opacity = np.concatenate([np.repeat(levels, n_alive // 3), np.full(n_dead, 0.004)])
    opacity = np.random.default_rng(1).permutation(opacity)
    p = _model(opacity)
    (v0, m0) = _snapshot(p)
    strategy = MCMCStrategy(MCMCConfig())
    rng = np.random.default_rng(5)
    assert strategy._relocate(p, rng) == n_dead
    v1, m1 = _snapshot(p)
    dead = _sigmoid(v0["opacities"]) <= 0.005
    assert dead.sum() == n_dead
    # sources: the alive rows each dead row now equals (means are distinct per row, so they identify the source)
    index = {tuple(m): i for i, m in enumerate(v0["means"]) if not dead[i]}
    src = np.array([index[tuple(m)] for m in v1["means"][dead]])
    for key in v1:
        np.testing.assert_array_equal(v1[key][dead], v1[key][src], err_msg=key)
    # drawn in proportion to opacity: counts per level against the expectation (5 standard deviations)
    o_src = np.round(_sigmoid(v0["opacities"][src]), 3)
    prob = levels / levels.sum()
    for level, q in zip(levels, prob):
        count = np.sum(np.isclose(o_src, level))
        assert abs(count - n_dead * q) < 5 * math.sqrt(n_dead * q * (1 - q)), (level, count)
    # the correction: a source drawn k times is shared by k + 1 copies
    written = np.zeros(len(opacity), bool)
    written[src] = written[dead] = True
    copies = np.bincount(src, minlength=len(opacity))[src] + 1
    assert copies.max() > 50
    copies = np.minimum(copies, 50)              # (the correction's table ends at 50 copies, as gsplat's)
    o_old, o_new = _sigmoid(v0["opacities"][src]), _sigmoid(v1["opacities"][src])
    np.testing.assert_allclose(1 - (1 - o_new) ** copies, o_old, rtol=2e-6)
    expect_o, expect_s = relocation(o_old, np.exp(v0["scales"][src].astype(np.float64)), copies)
    np.testing.assert_allclose(np.exp(v1["scales"][src].astype(np.float64)), expect_s, rtol=2e-6)
    for key in v1:
        np.testing.assert_array_equal(v1[key][~written], v0[key][~written], err_msg=key)
        for m_new, m_old in zip(m1[key], m0[key]):
            assert np.all(m_new[written] == 0) and np.all(m_old[written] != 0), key
            np.testing.assert_array_equal(m_new[~written], m_old[~written], err_msg=key)


def test_growth_follows_the_rate_and_never_exceeds_the_cap():
    """Each refinement adds floor(1.05 n) - n rows (copies of rows drawn by opacity, with the correction and zero
    moments; the first n rows keep theirs unless drawn) until the cap, then none."""
    rng = np.random.default_rng(2)
    p = _model(rng.uniform(0.05, 0.95, 200))
    cap = 260
    strategy = MCMCStrategy(MCMCConfig(cap_max=cap, refine_start_iter=0, refine_every=1))
    state = strategy.initialize_state(p.n)
    sizes = [p.n]
    for step in range(1, 9):
        n = p.n
        v0, m0 = _snapshot(p)
        will_change = strategy.replaces_parameters_at(p, step)
        info = strategy.step_post_backward(p, state, step, None)
        assert info.n == p.n == min(cap, int(1.05 * n)) and info.added == p.n - n and info.relocated == 0
        assert info.changed == (info.added > 0) == will_change   # (the trainer steps Adam when it changes nothing)
        sizes.append(p.n)
        v1, m1 = _snapshot(p)
        if info.added:
            # (a source: a row among the first n equal to the new row in every parameter, with zero moments)
            flat = np.concatenate([v1[k].reshape(p.n, -1) for k in sorted(v1)], axis=1)
            sources = [int(np.flatnonzero(np.all(flat[:n] == row, axis=1))[0]) for row in flat[n:]]
            for key in v1:
                assert all(np.all(m[n:] == 0) and np.all(m[sources] == 0) for m in m1[key]), key
    assert sizes == [200, 210, 220, 231, 242, 254, 260, 260, 260] and state.draws == 8
    logit = np.array(p["opacities"].array, np.float32)
    logit[0] = -20.0                                      # (one dead Gaussian at the cap: it will be relocated)
    p.replace("opacities", mi.TensorXf(mi.Float(logit)))
    assert strategy.replaces_parameters_at(p, 9)


def test_budget_is_never_exceeded_in_training(scene, tmp_path):  # noqa: F811
    """A run whose random init (5000 points) exceeds the cap starts from a uniform subsample of the cap's size and
    never has more Gaussians, through relocations and growth; the PSNR rises."""
    from mi_gaussians.optim.trainer import Trainer

    cfg = dataclasses.replace(small_config(300), strategy="mcmc",
                              mcmc=MCMCConfig(cap_max=3000, refine_start_iter=50, refine_every=50))
    tr = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    assert tr.params.n == 3000
    before = tr._test_psnr()
    metrics = tr.run()
    assert max(tr.history.gaussians) <= 3000 and metrics["gaussians"] <= 3000
    # refinements at 100, 150, 200, 250 (not 50: start < step; not 300, the last iteration: its refinement would
    # never be optimized, and is left pending in the checkpoint)
    assert tr.strategy_state.draws == 4 and tr._refine_at == 300
    assert metrics["mean"]["psnr"] > before + 3


def test_frozen_mcmc_training_equals_traced_training(scene, one_thread):  # noqa: F811
    """With relocation and growth every 40 iterations, the regularizers and the position noise: the frozen loop
    ends with the traced loop's model, moments and losses, bit for bit."""
    steps = 130
    cfg = dataclasses.replace(small_config(300), strategy="mcmc",
                              mcmc=MCMCConfig(cap_max=6000, refine_start_iter=20, refine_every=40))
    frozen = _train(scene, cfg, steps)
    traced = _train(scene, dataclasses.replace(cfg, freeze=False), steps)
    assert frozen.train_step.recordings >= 1 and frozen.params.n > 5000
    assert_same_training(frozen, traced)


def test_position_noise_covariance_and_gating():
    """z ~ N(0, I) scaled by lr * noise_lr and the opacity gate, times Sigma = R diag(s^2) R^T: the empirical
    covariance of many rows of one Gaussian is c^2 Sigma^2; an opaque Gaussian does not move; the noise is keyed
    by the iteration; an inactive step adds none."""
    n = 40_000
    q = np.array([0.9, 0.2, -0.3, 0.1])
    scales = np.log([0.02, 0.05, 0.1])
    opac = np.where(np.arange(n) < n - 10, -6.0, 6.0)       # the last 10 rows opaque
    g = Gaussians.from_numpy(np.zeros((n, 3)), np.tile(scales, (n, 1)), np.tile(q, (n, 1)), opac,
                             np.zeros((n, 3)), np.zeros((n, 0, 3)))
    p = GaussianAdam(g, OptimConfig(sh_degree=0), EXTENT)
    cfg = MCMCConfig(noise_lr=5e5)
    strategy = MCMCStrategy(cfg, seed=3)
    lr = 1.6e-4
    noise = np.array(strategy.position_noise(p, dr.opaque(mi.UInt32, 7), mi.Float(lr))).T
    o = 1 / (1 + math.exp(6.0))
    c = lr * cfg.noise_lr / (1 + math.exp(-100 * ((1 - o) - 0.995)))
    qn = q / np.linalg.norm(q)
    w, x, y, z = qn
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    sigma = R @ np.diag(np.exp(2 * scales)) @ R.T
    expect = c * c * sigma @ sigma
    emp = np.cov(noise[: n - 10].T)
    np.testing.assert_allclose(emp, expect, atol=0.03 * np.abs(expect).max())
    assert np.abs(noise[n - 10:]).max() < 1e-12 * np.abs(noise[: n - 10]).max() + 1e-30
    again = np.array(strategy.position_noise(p, dr.opaque(mi.UInt32, 7), mi.Float(lr))).T
    other = np.array(strategy.position_noise(p, dr.opaque(mi.UInt32, 8), mi.Float(lr))).T
    np.testing.assert_array_equal(again, noise)
    assert np.corrcoef(other[:1000, 0], noise[:1000, 0])[0, 1] < 0.2
    before = p.gaussians.numpy()["means"]
    strategy.step_post_update(p, None, dr.opaque(mi.UInt32, 7), mi.Float(lr), active=dr.opaque(mi.Bool, False))
    np.testing.assert_array_equal(p.gaussians.numpy()["means"], before)
    strategy.step_post_update(p, None, dr.opaque(mi.UInt32, 7), mi.Float(lr), active=dr.opaque(mi.Bool, True))
    np.testing.assert_allclose(p.gaussians.numpy()["means"], noise, rtol=1e-6, atol=1e-12)


def test_regularization_value_and_gradient():
    rng = np.random.default_rng(4)
    n = 50
    p = _model(rng.uniform(0.05, 0.95, n))
    p.clear_grads()
    strategy = MCMCStrategy(MCMCConfig(opacity_reg=0.01, scale_reg=0.02))
    reg = strategy.regularization(p)
    v = p.gaussians.numpy()
    o, s = _sigmoid(v["opacities"]), np.exp(v["scales"].astype(np.float64))
    assert float(reg[0]) == pytest.approx(0.01 * o.mean() + 0.02 * s.mean(), rel=1e-6)
    dr.backward(reg)
    np.testing.assert_allclose(np.array(dr.grad(p["opacities"])), 0.01 * o * (1 - o) / n, rtol=1e-5)
    np.testing.assert_allclose(np.array(dr.grad(p["scales"])).reshape(n, 3), 0.02 * s / (3 * n), rtol=1e-5)
    assert MCMCStrategy(MCMCConfig(opacity_reg=0, scale_reg=0)).regularization(p) is None


def test_state_checkpoint_and_other_strategy_refused():
    from mi_gaussians.config import DensifyConfig
    from mi_gaussians.optim.densify import DefaultStrategy

    s = MCMCStrategy(MCMCConfig(), seed=9)
    st = s.initialize_state(10)
    st.draws = 4
    arrays, meta = s.export_state(st)
    assert arrays == {} and s.import_state(arrays, meta, 10).draws == 4
    d = DefaultStrategy(DensifyConfig(), 1.0)
    d_arrays, d_meta = d.export_state(d.initialize_state(10))
    with pytest.raises(ValueError, match="another densification strategy"):
        s.import_state(d_arrays, d_meta, 10)
    with pytest.raises(ValueError, match="another densification strategy"):
        d.import_state(arrays, meta, 10)


def _mi_gs(*args):
    from test_cli import run

    return run(*args)


def test_cli_mcmc_run_and_misuse(scene, tmp_path):  # noqa: F811
    out = tmp_path / "run"
    r = _mi_gs("optimize", scene, "-o", out, "--iterations", "120", "--strategy", "mcmc", "--max-gaussians", "2000",
               "--random-points", "1500", "--eval-every", "0", "--quiet", "--set", "mcmc.refine_start_iter=10",
               "--set", "mcmc.refine_every=20")
    assert r.returncode == 0, r.stderr
    saved = json.loads((out / "config.json").read_text())["train"]
    assert saved["strategy"] == "mcmc" and saved["mcmc"]["cap_max"] == 2000
    assert saved["mcmc"]["refine_stop_iter"] == 100                   # 120 * 5 / 6: the paper's proportion
    # refinements at 20, 40, 60, 80: 1500 -> 1575 -> 1653 -> 1735 -> 1821
    history = json.loads((out / "history.json").read_text())
    assert max(history["gaussians"]) == 1821 and json.loads((out / "metrics.json").read_text())["gaussians"] == 1821
    r = _mi_gs("optimize", scene, "-o", out, "--iterations", "150", "--resume", "--max-gaussians", "3000", "--quiet")
    assert r.returncode == 2 and "mcmc.cap_max" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = _mi_gs("optimize", scene, "-o", out, "--iterations", "150", "--resume", "--quiet")
    assert r.returncode == 0, r.stderr
    for bad, words in ((["--max-gaussians", "10"], "--strategy mcmc"), (["--set", "strategy=sgd"], "sgd"),
                       (["--strategy", "mcmc", "--set", "mcmc.init_opacity=1.5"], "init_opacity"),
                       # an option of the other strategy would be silently ignored: refused
                       (["--strategy", "mcmc", "--absgrad"], "--absgrad"),
                       (["--set", "strategy=mcmc", "--set", "densify.absgrad=true"], "--absgrad"),
                       (["--strategy", "mcmc", "--set", "densify.grad_threshold=0.001"], "densify.grad_threshold"),
                       (["--set", "mcmc.noise_lr=1000"], "mcmc.noise_lr")):
        r = _mi_gs("optimize", scene, "-o", tmp_path / "bad", *bad, "--quiet")
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "bad").exists()
        assert not (tmp_path / "bad").exists()


def test_resumed_mcmc_run_equals_an_uninterrupted_one(scene, tmp_path, one_thread):  # noqa: F811
    """A run stopped at iteration 60 (after relocations and growth; 60 is a refinement iteration, whose refinement
    the checkpoint holds as pending) and resumed from its checkpoint ends, at 100, with the model of a run that was
    never stopped: the draws' counter and the noise's key come back."""
    cfg = dataclasses.replace(small_config(100), strategy="mcmc", checkpoint_every=1000, eval_every=0,
                              mcmc=MCMCConfig(cap_max=6000, refine_start_iter=10, refine_every=20))
    resumed, whole = stopped_and_resumed(scene, cfg, tmp_path)
    # 20, 40, 60, 80 (100 is the last iteration: its refinement is left pending)
    assert resumed.strategy_state.draws == whole.strategy_state.draws == 4
    assert_same_training(resumed, whole)
