"""The parameter owner GaussianAdam (mi_gaussians.optim.adam): Adam over Gaussians and its row operations.

Why row operations exist: Dr.Jit's ``opt[key] = value`` RESETS a parameter's Adam state (t = 0, zero moments) whenever
the shape changes (``test_trap_plain_assignment_of_a_new_shape_resets_state``), so densification must gather /
concatenate the moments itself. Here: kept rows keep bit-identical values and moments, new rows get zero moments,
t and the learning rates survive, and the next Adam step matches a NumPy Adam that carries the same state.
"""

from __future__ import annotations

import zlib

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_gaussians.config import OptimConfig
from mi_gaussians.model.gaussians import PARAMETER_NAMES, Gaussians
from mi_gaussians.optim.adam import GaussianAdam

EXTENT = 2.5
B1, B2 = 0.9, 0.999


def make_gaussians(n=7, degree=1, seed=0) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return Gaussians.from_numpy(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) - 3.0, rng.normal(size=(n, 4)),
                                rng.normal(size=n), rng.normal(size=(n, 3)), rng.normal(size=(n, k, 3)))


def weights(key, shape, salt=0):
    """Fixed, distinct, nonzero per-element weights so that every element gets its own gradient."""
    rng = np.random.default_rng([zlib.crc32(key.encode()), salt])
    return rng.uniform(0.5, 2.0, size=shape).astype(np.float32) * rng.choice([-1.0, 1.0], size=shape)


def loss_and_backward(g: Gaussians, salt=0):
    """loss = sum_k sum(w_k * p_k + 0.5 p_k^2): gradient w_k + p_k, nonzero everywhere."""
    loss = mi.Float(0.0)
    for key in PARAMETER_NAMES:
        p = getattr(g, key)
        if dr.width(p) == 0:
            continue
        w = mi.Float(weights(key, tuple(p.shape), salt).reshape(-1))
        loss = loss + dr.sum(w * p.array + 0.5 * dr.square(p.array))
    dr.backward(loss)


def expected_grad(values: dict, key: str, salt=0) -> np.ndarray:
    return weights(key, values[key].shape, salt) + values[key]


def snapshot(opt) -> dict:
    out = {}
    for key in opt.keys():
        t, m, v = opt.moments(key)
        out[key] = dict(value=np.array(opt[key]).reshape(tuple(opt[key].shape)), m=m, v=v, t=t,
                        lr=opt.learning_rate(key))
    return out


@pytest.fixture
def trained():
    """An Adam after 3 real steps (nonzero moments), and its Gaussians synchronized."""
    opt = GaussianAdam(make_gaussians(), OptimConfig(), EXTENT)
    for i in range(3):
        loss_and_backward(opt.gaussians, salt=i)
        opt.step()
    return opt


def numpy_adam_step(value, grad, m, v, t, lr, eps=1e-15):
    """One Adam step in float64 (Dr.Jit's update rule: bias-corrected step with eps^2 inside the root for tiny eps)."""
    b1, b2 = float(np.float32(B1)), float(np.float32(B2))   # Dr.Jit's moment EMAs use the float32 betas
    m1 = b1 * m + (1 - b1) * grad
    v1 = b2 * v + (1 - b2) * grad * grad
    t1 = t + 1
    scale = lr * np.sqrt(1 - B2 ** t1) / (1 - B1 ** t1)
    return value - scale * m1 / np.sqrt(v1 + eps * eps), m1, v1


# ---------------------------------------------------------------------------------------------- construction
def test_make_optimizer_learning_rates_and_eps():
    cfg = OptimConfig()
    g = make_gaussians()
    opt = GaussianAdam(g, cfg, EXTENT)
    assert opt.epsilon == cfg.adam_eps == 1e-15
    assert opt.betas == (B1, B2)
    assert opt.keys() == list(PARAMETER_NAMES) and opt.n == 7
    assert opt.learning_rate("means") == pytest.approx(1.6e-4 * EXTENT)
    assert opt.learning_rate("sh_dc") == pytest.approx(2.5e-3)
    assert opt.learning_rate("sh_rest") == pytest.approx(2.5e-3 / 20)
    assert opt.learning_rate("opacities") == pytest.approx(cfg.opacity_lr)
    assert opt.learning_rate("scales") == pytest.approx(5e-3)
    assert opt.learning_rate("rotations") == pytest.approx(1e-3)
    for key in PARAMETER_NAMES:
        assert tuple(opt[key].shape) == tuple(getattr(g, key).shape)
        np.testing.assert_array_equal(np.array(opt[key]), np.array(getattr(g, key)))
    assert all(opt[k] is not getattr(g, k) for k in PARAMETER_NAMES)    # copies: g is not kept
    opt.set_learning_rate("means", 1e-3)
    assert opt.learning_rate("means") == 1e-3
    with pytest.raises(ValueError, match="no Gaussians"):
        GaussianAdam(make_gaussians(n=0), cfg, EXTENT)


def test_the_view_renders_the_optimizer_tensors(trained):
    opt = trained
    view = opt.gaussians
    for key in PARAMETER_NAMES:
        assert getattr(view, key) is opt[key]
        assert dr.grad_enabled(getattr(view, key))
    loss_and_backward(view, salt=4)          # gradients through the view reach what step() updates
    before = np.array(opt["scales"])
    opt.step()
    assert not np.array_equal(np.array(opt["scales"]), before)
    assert opt.gaussians.scales is opt["scales"] and view.scales is not opt["scales"]   # step replaced the tensor


def test_degree_0_leaves_sh_rest_unregistered():
    g = make_gaussians(n=5, degree=0)
    assert tuple(g.sh_rest.shape) == (5, 0, 3)
    opt = GaussianAdam(g, OptimConfig(), EXTENT)
    assert "sh_rest" not in opt and opt.keys() == [k for k in PARAMETER_NAMES if k != "sh_rest"]
    opt.keep(np.array([True, False, True, True, False]))
    g = opt.gaussians
    assert tuple(g.sh_rest.shape) == (3, 0, 3) and g.n == 3 and g.sh_degree == 0
    rows = {k: np.zeros((2,) + tuple(getattr(g, k).shape[1:]), np.float32) for k in PARAMETER_NAMES}
    opt.append(rows)  # (2, 0, 3) sh_rest rows are accepted and ignored
    g = opt.gaussians
    assert tuple(g.sh_rest.shape) == (5, 0, 3) and g.n == 5
    with pytest.raises(KeyError):
        opt.append({**rows, "sh_rest": np.zeros((2, 3, 3), np.float32)})


# ---------------------------------------------------------------------------------------------- the trap
def test_trap_plain_assignment_of_a_new_shape_resets_state(trained):
    """Why optimizer.py exists: Dr.Jit re-registers a parameter of a new shape with t = 0 and zero moments."""
    opt = trained
    adam = mi.ad.Adam(lr=0.1)
    adam["means"] = mi.TensorXf(dr.ones(mi.Float, 7 * 3), (7, 3))
    adam.set_learning_rate({"means": 0.01})
    dr.backward(dr.sum(adam["means"].array))
    adam.step()
    assert int(adam.state["means"][3][0][0]) == 1 and np.abs(np.array(adam.state["means"][3][1])).max() > 0
    adam["means"] = mi.TensorXf(dr.zeros(mi.Float, 4 * 3), (4, 3))    # 7 rows -> 4 rows
    t2, m2, v2, _ = adam.state["means"][3]
    assert int(t2[0]) == 0 and not np.array(m2).any() and not np.array(v2).any()
    assert adam.learning_rate("means") is None    # ... and the parameter's learning rate is gone too
    # GaussianAdam.keep carries them instead
    t, m, _ = opt.moments("means")
    opt.keep(np.arange(4))
    assert opt.moments("means")[0] == t == 3 and np.array_equal(opt.moments("means")[1], m[:4])
    assert opt.learning_rate("means") == pytest.approx(1.6e-4 * EXTENT)


def test_replace_values_same_shape_keeps_moments(trained):
    opt = trained
    before = snapshot(opt)["scales"]
    new = mi.TensorXf(dr.full(mi.Float, -2.0, 7 * 3), (7, 3))
    opt.replace("scales", new)
    after = snapshot(opt)["scales"]
    assert after["t"] == before["t"] and after["lr"] == before["lr"]
    np.testing.assert_array_equal(after["m"], before["m"])
    np.testing.assert_array_equal(after["v"], before["v"])
    np.testing.assert_array_equal(after["value"], np.full((7, 3), -2.0, np.float32))
    assert dr.grad_enabled(opt["scales"])
    with pytest.raises(ValueError, match="shape"):
        opt.replace("scales", mi.TensorXf(dr.zeros(mi.Float, 6), (2, 3)))


# ---------------------------------------------------------------------------------------------- prune
@pytest.mark.parametrize("mask_kind", ["numpy", "drjit", "indices"])
def test_prune_keeps_rows_values_and_moments_bit_exact(trained, mask_kind):
    opt = trained
    before = snapshot(opt)
    keep = np.array([True, False, True, True, False, False, True])
    rows = {"numpy": keep, "drjit": mi.Bool(keep), "indices": np.flatnonzero(keep)}[mask_kind]
    opt.keep(rows)
    after = snapshot(opt)
    assert opt.n == 4
    for key in PARAMETER_NAMES:
        a, b = after[key], before[key]
        assert a["t"] == b["t"] == 3 and a["lr"] == b["lr"]
        assert a["value"].shape == (4,) + b["value"].shape[1:]
        for f in ("value", "m", "v"):
            np.testing.assert_array_equal(a[f], b[f][keep])
        assert dr.grad_enabled(opt[key]) and type(opt[key]) is mi.TensorXf


def test_prune_then_step_matches_numpy_adam(trained):
    opt = trained
    keep = np.array([False, True, True, False, True, True, True])
    before = snapshot(opt)
    opt.keep(keep)
    vals = {k: before[k]["value"][keep] for k in PARAMETER_NAMES}
    loss_and_backward(opt.gaussians, salt=7)
    opt.step()
    for key in PARAMETER_NAMES:
        b = before[key]
        ref, m_ref, v_ref = numpy_adam_step(vals[key].astype(np.float64), expected_grad(vals, key, 7),
                                            b["m"][keep], b["v"][keep], b["t"], b["lr"])
        t, m, v = opt.moments(key)
        assert t == 4
        np.testing.assert_allclose(m, m_ref, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(v, v_ref, rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(np.array(opt[key]).reshape(ref.shape), ref, rtol=1e-5, atol=1e-7)


def test_row_changes_leave_fresh_leaves_without_gradient(trained):
    """Gradients are not carried (a trainer that skips the step after a row change would otherwise add them to the
    next backward pass); the next backward pass reaches the new tensors through the view."""
    opt = trained
    loss_and_backward(opt.gaussians, salt=5)
    assert np.array(dr.grad(opt["means"])).any()
    opt.keep(np.array([True, True, False, True, False, True, True]))
    opt.append({k: np.ones((1,) + tuple(opt[k].shape[1:]), np.float32) for k in PARAMETER_NAMES})
    vals = {k: np.array(opt[k]).reshape(tuple(opt[k].shape)) for k in PARAMETER_NAMES}
    for key in PARAMETER_NAMES:
        assert dr.grad_enabled(opt[key]) and not np.array(dr.grad(opt[key])).any()
    loss_and_backward(opt.gaussians, salt=6)
    for key in PARAMETER_NAMES:
        np.testing.assert_allclose(np.array(dr.grad(opt[key])).reshape(vals[key].shape),
                                   expected_grad(vals, key, 6), rtol=1e-6)


def test_prune_everything_raises(trained):
    opt = trained
    with pytest.raises(RuntimeError, match="every Gaussian"):
        opt.keep(np.zeros(7, bool))
    with pytest.raises(ValueError):
        opt.keep(np.ones(5, bool))


# ---------------------------------------------------------------------------------------------- append
def test_append_new_rows_get_zero_moments_and_then_train(trained):
    opt = trained
    before = snapshot(opt)
    rng = np.random.default_rng(3)
    new = {k: rng.normal(size=(2,) + before[k]["value"].shape[1:]).astype(np.float32) for k in PARAMETER_NAMES}
    new["sh_dc"] = mi.TensorXf(mi.Float(new["sh_dc"].reshape(-1)), (2, 3))   # TensorXf rows are accepted too
    opt.append(new)
    after = snapshot(opt)
    assert opt.n == 9
    new_np = {k: np.array(v).reshape((2,) + before[k]["value"].shape[1:]) for k, v in new.items()}
    for key in PARAMETER_NAMES:
        a, b = after[key], before[key]
        assert a["t"] == b["t"] == 3 and a["lr"] == b["lr"]
        for f in ("value", "m", "v"):
            np.testing.assert_array_equal(a[f][:7], b[f])
        np.testing.assert_array_equal(a["value"][7:], new_np[key])
        assert not a["m"][7:].any() and not a["v"][7:].any()
        assert not np.array(dr.grad(opt[key])).any()   # fresh leaves

    # the next real step: kept rows continue their moments, new rows start from zero; both move
    vals = {k: after[k]["value"] for k in PARAMETER_NAMES}
    loss_and_backward(opt.gaussians, salt=9)
    opt.step()
    for key in PARAMETER_NAMES:
        a = after[key]
        ref, m_ref, v_ref = numpy_adam_step(vals[key].astype(np.float64), expected_grad(vals, key, 9),
                                            a["m"], a["v"], a["t"], a["lr"])
        t, m, v = opt.moments(key)
        got = np.array(opt[key]).reshape(ref.shape)
        assert t == 4
        np.testing.assert_allclose(m, m_ref, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(v, v_ref, rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-7)
        assert np.all(got[7:] != vals[key][7:])   # the new rows were updated
        assert np.all(m[7:] != 0)


def test_new_rows_without_gradient_stay_put(trained):
    """After a row change with no new backward pass, Adam leaves zero-moment, zero-gradient rows exactly in place."""
    opt = trained
    new = {k: np.ones((1,) + tuple(opt[k].shape[1:]), np.float32) for k in PARAMETER_NAMES}
    opt.append(new)
    opt.step()
    for key in PARAMETER_NAMES:
        np.testing.assert_array_equal(np.array(opt[key]).reshape(tuple(opt[key].shape))[7:], new[key])


def test_append_validates(trained):
    opt = trained
    rows = {k: np.zeros((2,) + tuple(opt[k].shape[1:]), np.float32) for k in PARAMETER_NAMES}
    with pytest.raises(KeyError):
        opt.append({k: v for k, v in rows.items() if k != "opacities"})
    with pytest.raises(ValueError):
        opt.append({**rows, "means": np.zeros((2, 4), np.float32)})
    with pytest.raises(ValueError):
        opt.append({**rows, "means": np.zeros((3, 3), np.float32)})
    opt.append({k: v[:0] for k, v in rows.items()})    # zero new rows: a no-op
    assert opt["means"].shape[0] == 7 and opt.moments("means")[0] == 3


# ---------------------------------------------------------------------------------------------- moments
def test_reset_moments_all_and_selected_rows(trained):
    opt = trained
    before = snapshot(opt)
    opt.reset_moments("opacities")
    t, m, v = opt.moments("opacities")
    assert t == 3 and not m.any() and not v.any()
    np.testing.assert_array_equal(np.array(opt["opacities"]), before["opacities"]["value"])

    rows = np.array([False, True, False, False, True, False, False])
    for sel in (rows, np.flatnonzero(rows), mi.Bool(rows)):
        opt.reset_moments("sh_rest", sel)
        t, m, v = opt.moments("sh_rest")
        b = before["sh_rest"]
        assert t == 3
        assert not m[rows].any() and not v[rows].any()
        np.testing.assert_array_equal(m[~rows], b["m"][~rows])
        np.testing.assert_array_equal(v[~rows], b["v"][~rows])
    # other parameters untouched
    np.testing.assert_array_equal(opt.moments("means")[1], before["means"]["m"])


def test_export_import_state_round_trip(trained):
    opt = trained
    saved = opt.export_moments()
    before = snapshot(opt)
    opt2 = GaussianAdam(Gaussians.from_numpy(**opt.gaussians.numpy()), OptimConfig(), EXTENT)
    assert opt2.moments("means")[0] == 0
    opt2.import_moments(saved)
    after = snapshot(opt2)
    for key in PARAMETER_NAMES:
        assert after[key]["t"] == 3
        np.testing.assert_array_equal(after[key]["m"], before[key]["m"])
        np.testing.assert_array_equal(after[key]["v"], before[key]["v"])
    with pytest.raises(ValueError):
        opt2.import_moments({**saved, "means.m": np.zeros((3, 3), np.float32)})
    with pytest.raises(KeyError, match="sh_dc.v"):
        opt2.import_moments({k: (v * 0 if k.endswith(".m") else v) for k, v in saved.items() if k != "sh_dc.v"})
    for key in PARAMETER_NAMES:    # a refused import changes nothing
        np.testing.assert_array_equal(opt2.moments(key)[1], before[key]["m"])


def test_rows_returns_detached_copies(trained):
    opt = trained
    rows = opt.rows(np.array([4, 1]))
    for key in PARAMETER_NAMES:
        full = np.array(opt[key]).reshape(tuple(opt[key].shape))
        np.testing.assert_array_equal(np.array(rows[key]).reshape((2,) + full.shape[1:]), full[[4, 1]])
        assert not dr.grad_enabled(rows[key])
