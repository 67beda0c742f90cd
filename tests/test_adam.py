"""Adam over Gaussians and its row surgery (mi_gaussians.optim.optimizer).

The point of the module: Dr.Jit's ``opt[key] = value`` RESETS a parameter's Adam state (t = 0, zero moments) whenever
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
from mi_gaussians.model.gaussians import Gaussians
from mi_gaussians.optim import optimizer as O

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
    for key in O.PARAM_KEYS:
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
    for key in opt.state:
        t, m, v = O.moments(opt, key)
        out[key] = dict(value=np.array(opt[key]).reshape(tuple(opt[key].shape)), m=m, v=v, t=t,
                        lr=opt.learning_rate(key))
    return out


@pytest.fixture
def trained():
    """An Adam after 3 real steps (nonzero moments), and its Gaussians synchronized."""
    g = make_gaussians()
    opt = O.make_optimizer(g, OptimConfig(), EXTENT)
    O.sync_gaussians(opt, g)
    for i in range(3):
        loss_and_backward(g, salt=i)
        opt.step()
        O.sync_gaussians(opt, g)
    return g, opt


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
    opt = O.make_optimizer(g, cfg, EXTENT)
    assert isinstance(opt, mi.ad.Adam)
    assert opt.epsilon == cfg.adam_eps == 1e-15
    assert opt.beta_1 == B1 and opt.beta_2 == B2
    assert set(opt.keys()) == set(O.PARAM_KEYS)
    assert opt.learning_rate("means") == pytest.approx(1.6e-4 * EXTENT)
    assert opt.learning_rate("sh_dc") == pytest.approx(2.5e-3)
    assert opt.learning_rate("sh_rest") == pytest.approx(2.5e-3 / 20)
    assert opt.learning_rate("opacities") == pytest.approx(cfg.opacity_lr)
    assert opt.learning_rate("scales") == pytest.approx(5e-3)
    assert opt.learning_rate("rotations") == pytest.approx(1e-3)
    for key in O.PARAM_KEYS:
        assert tuple(opt[key].shape) == tuple(getattr(g, key).shape)
        np.testing.assert_array_equal(np.array(opt[key]), np.array(getattr(g, key)))
    O.set_position_lr(opt, 1e-3)
    assert opt.learning_rate("means") == 1e-3


def test_sync_gaussians_renders_the_optimizer_tensors(trained):
    g, opt = trained
    for key in O.PARAM_KEYS:
        assert getattr(g, key) is opt[key]
        assert dr.grad_enabled(getattr(g, key))


def test_degree_0_leaves_sh_rest_unregistered():
    g = make_gaussians(n=5, degree=0)
    assert tuple(g.sh_rest.shape) == (5, 0, 3)
    opt = O.make_optimizer(g, OptimConfig(), EXTENT)
    assert "sh_rest" not in opt
    O.sync_gaussians(opt, g)
    O.prune(opt, np.array([True, False, True, True, False]))
    O.sync_gaussians(opt, g)
    assert tuple(g.sh_rest.shape) == (3, 0, 3) and g.n == 3 and g.sh_degree == 0
    rows = {k: np.zeros((2,) + tuple(getattr(g, k).shape[1:]), np.float32) for k in O.PARAM_KEYS}
    O.append(opt, rows)  # (2, 0, 3) sh_rest rows are accepted and ignored
    O.sync_gaussians(opt, g)
    assert tuple(g.sh_rest.shape) == (5, 0, 3) and g.n == 5
    with pytest.raises(KeyError):
        O.append(opt, {**rows, "sh_rest": np.zeros((2, 3, 3), np.float32)})


# ---------------------------------------------------------------------------------------------- the trap
def test_trap_plain_assignment_of_a_new_shape_resets_state(trained):
    """Why optimizer.py exists: Dr.Jit re-registers a parameter of a new shape with t = 0 and zero moments."""
    g, opt = trained
    t, m, _ = O.moments(opt, "means")
    assert t == 3 and np.abs(m).max() > 0
    opt["means"] = mi.TensorXf(dr.zeros(mi.Float, 4 * 3), (4, 3))    # 7 rows -> 4 rows
    t2, m2, v2 = O.moments(opt, "means")
    assert t2 == 0 and not m2.any() and not v2.any()
    assert opt.learning_rate("means") is None    # ... and the parameter's learning rate is gone too


def test_replace_values_same_shape_keeps_moments(trained):
    g, opt = trained
    before = snapshot(opt)["scales"]
    new = mi.TensorXf(dr.full(mi.Float, -2.0, 7 * 3), (7, 3))
    O.replace_values(opt, "scales", new)
    after = snapshot(opt)["scales"]
    assert after["t"] == before["t"] and after["lr"] == before["lr"]
    np.testing.assert_array_equal(after["m"], before["m"])
    np.testing.assert_array_equal(after["v"], before["v"])
    np.testing.assert_array_equal(after["value"], np.full((7, 3), -2.0, np.float32))
    assert dr.grad_enabled(opt["scales"])
    with pytest.raises(ValueError, match="shape"):
        O.replace_values(opt, "scales", mi.TensorXf(dr.zeros(mi.Float, 6), (2, 3)))


# ---------------------------------------------------------------------------------------------- prune
@pytest.mark.parametrize("mask_kind", ["numpy", "drjit", "indices"])
def test_prune_keeps_rows_values_and_moments_bit_exact(trained, mask_kind):
    g, opt = trained
    before = snapshot(opt)
    keep = np.array([True, False, True, True, False, False, True])
    rows = {"numpy": keep, "drjit": mi.Bool(keep), "indices": np.flatnonzero(keep)}[mask_kind]
    O.prune(opt, rows)
    O.sync_gaussians(opt, g)
    after = snapshot(opt)
    assert g.n == 4
    for key in O.PARAM_KEYS:
        a, b = after[key], before[key]
        assert a["t"] == b["t"] == 3 and a["lr"] == b["lr"]
        assert a["value"].shape == (4,) + b["value"].shape[1:]
        for f in ("value", "m", "v"):
            np.testing.assert_array_equal(a[f], b[f][keep])
        assert dr.grad_enabled(opt[key]) and type(opt[key]) is mi.TensorXf


def test_prune_then_step_matches_numpy_adam(trained):
    g, opt = trained
    keep = np.array([False, True, True, False, True, True, True])
    before = snapshot(opt)
    O.prune(opt, keep)
    O.sync_gaussians(opt, g)
    vals = {k: before[k]["value"][keep] for k in O.PARAM_KEYS}
    loss_and_backward(g, salt=7)
    opt.step()
    O.sync_gaussians(opt, g)
    for key in O.PARAM_KEYS:
        b = before[key]
        ref, m_ref, v_ref = numpy_adam_step(vals[key].astype(np.float64), expected_grad(vals, key, 7),
                                            b["m"][keep], b["v"][keep], b["t"], b["lr"])
        t, m, v = O.moments(opt, key)
        assert t == 4
        np.testing.assert_allclose(m, m_ref, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(v, v_ref, rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(np.array(opt[key]).reshape(ref.shape), ref, rtol=1e-5, atol=1e-7)


def test_row_changes_leave_fresh_leaves_without_gradient(trained):
    """Gradients are not carried (a trainer that skips the step after a row change would otherwise add them to the
    next backward pass); the next backward pass reaches the new tensors through g."""
    g, opt = trained
    loss_and_backward(g, salt=5)
    assert np.array(dr.grad(opt["means"])).any()
    O.prune(opt, np.array([True, True, False, True, False, True, True]))
    O.append(opt, {k: np.ones((1,) + tuple(opt[k].shape[1:]), np.float32) for k in O.PARAM_KEYS})
    O.sync_gaussians(opt, g)
    vals = {k: np.array(opt[k]).reshape(tuple(opt[k].shape)) for k in O.PARAM_KEYS}
    for key in O.PARAM_KEYS:
        assert dr.grad_enabled(opt[key]) and not np.array(dr.grad(opt[key])).any()
    loss_and_backward(g, salt=6)
    for key in O.PARAM_KEYS:
        np.testing.assert_allclose(np.array(dr.grad(opt[key])).reshape(vals[key].shape),
                                   expected_grad(vals, key, 6), rtol=1e-6)


def test_prune_everything_raises(trained):
    g, opt = trained
    with pytest.raises(RuntimeError, match="every Gaussian"):
        O.prune(opt, np.zeros(7, bool))
    with pytest.raises(ValueError):
        O.prune(opt, np.ones(5, bool))


# ---------------------------------------------------------------------------------------------- append
def test_append_new_rows_get_zero_moments_and_then_train(trained):
    g, opt = trained
    before = snapshot(opt)
    rng = np.random.default_rng(3)
    new = {k: rng.normal(size=(2,) + before[k]["value"].shape[1:]).astype(np.float32) for k in O.PARAM_KEYS}
    new["sh_dc"] = mi.TensorXf(mi.Float(new["sh_dc"].reshape(-1)), (2, 3))   # TensorXf rows are accepted too
    O.append(opt, new)
    O.sync_gaussians(opt, g)
    after = snapshot(opt)
    assert g.n == 9
    new_np = {k: np.array(v).reshape((2,) + before[k]["value"].shape[1:]) for k, v in new.items()}
    for key in O.PARAM_KEYS:
        a, b = after[key], before[key]
        assert a["t"] == b["t"] == 3 and a["lr"] == b["lr"]
        for f in ("value", "m", "v"):
            np.testing.assert_array_equal(a[f][:7], b[f])
        np.testing.assert_array_equal(a["value"][7:], new_np[key])
        assert not a["m"][7:].any() and not a["v"][7:].any()
        assert not np.array(dr.grad(opt[key])).any()   # fresh leaves

    # the next real step: kept rows continue their moments, new rows start from zero; both move
    vals = {k: after[k]["value"] for k in O.PARAM_KEYS}
    loss_and_backward(g, salt=9)
    opt.step()
    O.sync_gaussians(opt, g)
    for key in O.PARAM_KEYS:
        a = after[key]
        ref, m_ref, v_ref = numpy_adam_step(vals[key].astype(np.float64), expected_grad(vals, key, 9),
                                            a["m"], a["v"], a["t"], a["lr"])
        t, m, v = O.moments(opt, key)
        got = np.array(opt[key]).reshape(ref.shape)
        assert t == 4
        np.testing.assert_allclose(m, m_ref, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(v, v_ref, rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-7)
        assert np.all(got[7:] != vals[key][7:])   # the new rows were updated
        assert np.all(m[7:] != 0)


def test_new_rows_without_gradient_stay_put(trained):
    """After a row change with no new backward pass, Adam leaves zero-moment, zero-gradient rows exactly in place."""
    g, opt = trained
    new = {k: np.ones((1,) + tuple(opt[k].shape[1:]), np.float32) for k in O.PARAM_KEYS}
    O.append(opt, new)
    opt.step()
    for key in O.PARAM_KEYS:
        np.testing.assert_array_equal(np.array(opt[key]).reshape(tuple(opt[key].shape))[7:], new[key])


def test_append_validates(trained):
    g, opt = trained
    rows = {k: np.zeros((2,) + tuple(opt[k].shape[1:]), np.float32) for k in O.PARAM_KEYS}
    with pytest.raises(KeyError):
        O.append(opt, {k: v for k, v in rows.items() if k != "opacities"})
    with pytest.raises(ValueError):
        O.append(opt, {**rows, "means": np.zeros((2, 4), np.float32)})
    with pytest.raises(ValueError):
        O.append(opt, {**rows, "means": np.zeros((3, 3), np.float32)})
    O.append(opt, {k: v[:0] for k, v in rows.items()})    # zero new rows: a no-op
    assert opt["means"].shape[0] == 7 and O.moments(opt, "means")[0] == 3


# ---------------------------------------------------------------------------------------------- moments
def test_reset_moments_all_and_selected_rows(trained):
    g, opt = trained
    before = snapshot(opt)
    O.reset_moments(opt, "opacities")
    t, m, v = O.moments(opt, "opacities")
    assert t == 3 and not m.any() and not v.any()
    np.testing.assert_array_equal(np.array(opt["opacities"]), before["opacities"]["value"])

    rows = np.array([False, True, False, False, True, False, False])
    for sel in (rows, np.flatnonzero(rows), mi.Bool(rows)):
        O.reset_moments(opt, "sh_rest", sel)
        t, m, v = O.moments(opt, "sh_rest")
        b = before["sh_rest"]
        assert t == 3
        assert not m[rows].any() and not v[rows].any()
        np.testing.assert_array_equal(m[~rows], b["m"][~rows])
        np.testing.assert_array_equal(v[~rows], b["v"][~rows])
    # other parameters untouched
    np.testing.assert_array_equal(O.moments(opt, "means")[1], before["means"]["m"])


def test_export_import_state_round_trip(trained):
    g, opt = trained
    saved = O.export_state(opt)
    before = snapshot(opt)
    opt2 = O.make_optimizer(Gaussians.from_numpy(**g.numpy()), OptimConfig(), EXTENT)
    assert O.moments(opt2, "means")[0] == 0
    O.import_state(opt2, saved)
    after = snapshot(opt2)
    for key in O.PARAM_KEYS:
        assert after[key]["t"] == 3
        np.testing.assert_array_equal(after[key]["m"], before[key]["m"])
        np.testing.assert_array_equal(after[key]["v"], before[key]["v"])
    with pytest.raises(ValueError):
        O.import_state(opt2, {**saved, "means.m": np.zeros((3, 3), np.float32)})
