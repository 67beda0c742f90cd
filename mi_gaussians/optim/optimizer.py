"""Adam over a :class:`Gaussians` model, and row surgery on its state (the ONLY code that touches ``opt.state``).

Mitsuba's ``mi.ad.Adam`` is ``drjit.opt.Adam``. Each parameter's entry is::

    opt.state[key] = (value, promoted, lr, (t, m, v, vmax))

``value`` is the grad-enabled parameter (a ``TensorXf`` here), ``promoted`` the fp16 -> fp32 flag, ``lr`` the
parameter's learning rate (``None``: the global one), ``t`` the step count (a 1-element ``UInt32``), ``m`` and ``v``
the first and second moments (flat arrays of the value's width) and ``vmax`` AMSGrad's running maximum (or ``None``).

The trap this module exists for: ``opt[key] = value`` keeps the state only when ``value`` has the shape of the current
parameter; a parameter of a NEW shape (densification adds and removes rows) is re-registered with ``t = 0`` and zero
moments, which throws away every Gaussian's Adam history and restarts bias correction. 3DGS instead keeps the step
count and the moments of surviving rows, and gives new rows zero moments. :func:`prune` and :func:`append` do that by
gathering / concatenating the value and every moment row-wise (rows = the first axis, N) on the device.

After a row change every parameter is a fresh AD leaf with a zero gradient, like the reference's freshly built
``nn.Parameter``s (whose ``.grad`` is None, so PyTorch's Adam skips them on that iteration). Gradients are deliberately
NOT carried over: a trainer that skips ``opt.step()`` after a row change (as the reference effectively does) renders
and backpropagates into these same leaves next, and a carried gradient would be added to the next one. A trainer that
steps anyway gets a zero-gradient Adam step: rows with zero moments (new rows) stay exactly in place, kept rows coast
on their decayed momentum.

SH degree 0: ``sh_rest`` is then an (N, 0, 3) tensor, and Dr.Jit refuses to register an empty parameter, so it is
simply not registered; :func:`sync_gaussians` gives ``g`` an empty (N, 0, 3) tensor of the right N.

Typical loop (the trainer)::

    opt = make_optimizer(g, cfg, extent)
    sync_gaussians(opt, g)                     # g now renders opt's grad-enabled tensors
    for it in range(1, iters + 1):
        set_position_lr(opt, schedule(it))
        out = render(g, cam); dr.backward(loss(out))
        info = strategy.step_post_backward(it, g, opt, out, W, H)   # prune / append through this module
        if not info["changed"]:
            opt.step()                         # the reference's Adam skips the rebuilt parameters
        sync_gaussians(opt, g)
"""

from __future__ import annotations

from typing import Mapping

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import OptimConfig
from ..model.gaussians import Gaussians

PARAM_KEYS = ("means", "scales", "rotations", "opacities", "sh_dc", "sh_rest")


# ---------------------------------------------------------------------------------------------- construction
def learning_rates(cfg: OptimConfig, extent: float) -> dict[str, float]:
    """The per-parameter learning rates of 3DGS at the start of training (position: ``position_lr_init * extent``)."""
    return {
        "means": float(cfg.position_lr_init) * float(extent),
        "scales": float(cfg.scaling_lr),
        "rotations": float(cfg.rotation_lr),
        "opacities": float(cfg.opacity_lr),
        "sh_dc": float(cfg.feature_lr),
        "sh_rest": float(cfg.feature_lr) / 20.0,
    }


def make_optimizer(g: Gaussians, cfg: OptimConfig, extent: float) -> "mi.ad.Adam":
    """An Adam (eps ``cfg.adam_eps``, betas 0.9 / 0.999) holding copies of ``g``'s six parameters.

    Every registered parameter has its own learning rate (:func:`learning_rates`); the global rate is 0, so a
    parameter registered later without a rate of its own stays put instead of moving at a guessed rate.
    ``sh_rest`` of SH degree 0 is empty and therefore not registered (see the module docstring).
    Call :func:`sync_gaussians` afterwards so that ``g`` renders the optimizer's grad-enabled tensors.
    """
    if g.n == 0:
        raise ValueError("make_optimizer: the model has no Gaussians (Dr.Jit refuses empty parameters)")
    opt = mi.ad.Adam(lr=0.0, epsilon=float(cfg.adam_eps))
    lrs = learning_rates(cfg, extent)
    for key in PARAM_KEYS:
        value = getattr(g, key)
        if dr.width(value) == 0:          # sh_rest of degree 0
            continue
        opt[key] = value
    opt.set_learning_rate({k: lrs[k] for k in PARAM_KEYS if k in opt})
    return opt


def set_position_lr(opt, lr: float) -> None:
    """Set the learning rate of the means (the scheduled one); a Python float, so no kernel recompiles."""
    opt.set_learning_rate({"means": float(lr)})


def _num_rows(opt) -> int:
    return int(opt.state["means"][0].shape[0])


def sync_gaussians(opt, g: Gaussians) -> None:
    """Point ``g``'s fields at the optimizer's current (grad-enabled) tensors, so that rendering ``g`` differentiates
    w.r.t. what ``opt.step()`` updates. ``sh_rest`` not registered (degree 0) becomes an empty (N, K - 1, 3) tensor."""
    n = _num_rows(opt)
    for key in PARAM_KEYS:
        if key in opt.state:
            setattr(g, key, opt.state[key][0])
        else:
            old = getattr(g, key)
            shape = (n,) + tuple(old.shape[1:])
            if int(np.prod(shape)) != 0:
                raise RuntimeError(f"sync_gaussians: parameter {key!r} is not registered but g.{key} is non-empty")
            setattr(g, key, type(old)(dr.zeros(type(old.array), 0), shape))


# ---------------------------------------------------------------------------------------------- row surgery helpers
def _owned(tp, a: np.ndarray):
    """A Dr.Jit array of type ``tp`` owning a copy of the flat NumPy array ``a`` (arrays made from NumPy are zero-copy
    views with foreign alignment, which makes kernels recompile per data set: see drjit-notes.md)."""
    out = dr.zeros(tp, a.size)
    if a.size:
        dr.scatter(out, tp(np.ascontiguousarray(a).reshape(-1)), dr.arange(mi.UInt32, a.size))
    return out


def _row_index(rows, n: int) -> "mi.UInt32":
    """A ``UInt32`` index array from a boolean mask of length n (NumPy or Dr.Jit) or from row indices."""
    if isinstance(rows, np.ndarray):
        if rows.dtype == np.bool_:
            if rows.shape != (n,):
                raise ValueError(f"row mask of shape {rows.shape}, expected ({n},)")
            return _owned(mi.UInt32, np.flatnonzero(rows).astype(np.uint32))
        idx = np.asarray(rows, np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise IndexError(f"row index out of range 0..{n - 1}")
        return _owned(mi.UInt32, idx.astype(np.uint32))
    if isinstance(rows, (list, tuple)):
        return _row_index(np.asarray(rows), n)
    if dr.is_array_v(rows) and dr.type_v(rows) == dr.VarType.Bool:
        if dr.width(rows) != n:
            raise ValueError(f"row mask of width {dr.width(rows)}, expected {n}")
        return dr.compress(rows)
    if dr.is_array_v(rows) and dr.is_integral_v(rows):
        return mi.UInt32(rows)
    raise TypeError(f"rows must be a boolean mask or an index array, got {type(rows).__name__}")


def _flat_index(rows: "mi.UInt32", row_size: int) -> "mi.UInt32":
    """Flat element indices of ``rows`` in a row-major (N, row_size) array: row r -> r*row_size + [0, row_size)."""
    if row_size == 1 or dr.width(rows) == 0:    # (Dr.Jit arithmetic refuses to mix a width-0 and a literal)
        return rows
    return dr.repeat(rows * row_size, row_size) + dr.tile(dr.arange(mi.UInt32, row_size), dr.width(rows))


def _gather_rows(flat, rows: "mi.UInt32", row_size: int):
    """Rows ``rows`` of a flat row-major array (a detached, lazily evaluated gather)."""
    return dr.gather(type(flat), dr.detach(flat), _flat_index(rows, row_size))


def concat(arrays: list):
    """``dr.concat`` of flat arrays that tolerates empty ones (``dr.concat`` fails on an empty operand)."""
    nonempty = [a for a in arrays if dr.width(a)]
    if not nonempty:
        return arrays[0]
    return nonempty[0] if len(nonempty) == 1 else dr.concat(nonempty)


def _row_size(value) -> int:
    return int(np.prod(value.shape[1:])) if len(value.shape) > 1 else 1


def _make_value(value_tp, flat, shape, promoted: bool):
    """Rebuild a parameter as ``Optimizer.__setitem__`` would: detached, opaque, grad-enabled (fp32 if promoted)."""
    if dr.width(flat) == 0:
        raise RuntimeError("densification would leave a parameter empty (Dr.Jit refuses empty parameters)")
    new = value_tp(flat, tuple(shape)) if dr.is_tensor_v(value_tp) else value_tp(flat)
    new = dr.detach(new)
    dr.make_opaque(new)
    dr.enable_grad(new)
    return new


def _store(opt, key: str, value_flat, shape, m, v, vmax) -> None:
    """Write a new value (a fresh leaf, zero gradient) and moments for ``key``, keeping promoted, lr and t."""
    value, promoted, lr, (t, _, _, _) = opt.state[key]
    dr.make_opaque(m, v)
    if vmax is not None:
        dr.make_opaque(vmax)
    new = _make_value(type(value), value_flat, shape, promoted)
    opt.state[key] = (new, promoted, lr, (t, m, v, vmax))


# ---------------------------------------------------------------------------------------------- public row surgery
def prune(opt, keep) -> None:
    """Keep the rows ``keep`` (boolean mask of length N, NumPy or ``mi.Bool``; or row indices) of every parameter and
    of its first and second moments (and ``vmax``). The step count ``t`` and the learning rate are kept; the new
    values are fresh leaves (zero gradient). Removing every row raises (Dr.Jit refuses empty parameters)."""
    n = _num_rows(opt)
    idx = _row_index(keep, n)
    if dr.width(idx) == 0:
        raise RuntimeError("prune would remove every Gaussian (Dr.Jit refuses empty parameters)")
    for key in list(opt.state.keys()):
        value, _, _, (t, m, v, vmax) = opt.state[key]
        if value.shape[0] != n:
            raise RuntimeError(f"parameter {key!r} has {value.shape[0]} rows, 'means' has {n}")
        rs = _row_size(value)
        shape = (dr.width(idx),) + tuple(value.shape[1:])
        _store(opt, key, _gather_rows(value.array, idx, rs), shape,
               _gather_rows(m, idx, rs), _gather_rows(v, idx, rs),
               None if vmax is None else _gather_rows(vmax, idx, rs))
    dr.eval(opt.state)


def _as_flat(x, flat_tp) -> tuple:
    """(flat Dr.Jit array, shape) of a NumPy array or a Dr.Jit tensor."""
    if isinstance(x, np.ndarray) or isinstance(x, (list, tuple)):
        a = np.ascontiguousarray(x, dtype=np.float32)
        return _owned(flat_tp, a), a.shape
    if dr.is_tensor_v(x):
        return flat_tp(dr.detach(x).array), tuple(x.shape)
    raise TypeError(f"new rows must be NumPy arrays or Dr.Jit tensors, got {type(x).__name__}")


def append(opt, new_rows: Mapping[str, object]) -> None:
    """Concatenate ``new_rows[key]`` (shape (k, *row_shape), NumPy or ``TensorXf``) after the rows of every parameter.

    Every registered parameter must be given, with the same k. New rows get zero first and second moments (and
    ``vmax``); kept rows keep theirs; ``t`` and the learning rate are kept; the new values are fresh leaves (zero
    gradient). A key that is not registered (``sh_rest`` of degree 0) is accepted only when its rows are empty."""
    n = _num_rows(opt)
    for key in new_rows:
        if key not in opt.state:
            if key not in PARAM_KEYS:
                raise KeyError(f"append: unknown parameter {key!r}")
            flat, _ = _as_flat(new_rows[key], mi.Float)
            if dr.width(flat) != 0:
                raise KeyError(f"append: parameter {key!r} is not registered but its new rows are not empty")
    missing = [k for k in opt.state if k not in new_rows]
    if missing:
        raise KeyError(f"append: new rows missing for {missing}")
    prepared = {}
    k_rows = None
    for key, (value, _, _, _) in opt.state.items():
        flat_tp = type(value.array)
        flat, shape = _as_flat(new_rows[key], flat_tp)
        if tuple(shape[1:]) != tuple(value.shape[1:]):
            raise ValueError(f"append: {key} rows of shape {tuple(shape[1:])}, expected {tuple(value.shape[1:])}")
        if k_rows is None:
            k_rows = shape[0]
        elif shape[0] != k_rows:
            raise ValueError(f"append: {key} has {shape[0]} new rows, others have {k_rows}")
        prepared[key] = flat
    if not k_rows:
        return
    for key in list(opt.state.keys()):
        value, _, _, (t, m, v, vmax) = opt.state[key]
        if value.shape[0] != n:
            raise RuntimeError(f"parameter {key!r} has {value.shape[0]} rows, 'means' has {n}")
        flat_tp = type(value.array)
        k = dr.width(prepared[key])
        zeros = dr.zeros(flat_tp, k)
        shape = (n + k_rows,) + tuple(value.shape[1:])
        _store(opt, key, concat([dr.detach(value.array), prepared[key]]), shape,
               concat([m, zeros]), concat([v, zeros]),
               None if vmax is None else concat([vmax, zeros]))
    dr.eval(opt.state)


def reset_moments(opt, key: str, rows=None) -> None:
    """Zero the first and second moments (and ``vmax``) of ``key``, for all rows or for ``rows`` (boolean mask or
    indices). ``t``, the value and its gradient are untouched (3DGS's opacity reset)."""
    value, promoted, lr, (t, m, v, vmax) = opt.state[key]
    flat_tp = type(m)
    if rows is None:
        m, v = dr.zeros(flat_tp, dr.width(m)), dr.zeros(flat_tp, dr.width(v))
        vmax = None if vmax is None else dr.zeros(flat_tp, dr.width(vmax))
    else:
        idx = _flat_index(_row_index(rows, int(value.shape[0])), _row_size(value))
        hit = dr.zeros(dr.mask_t(flat_tp), dr.width(m))    # a fresh array: scattering into it is safe
        dr.scatter(hit, True, idx)
        m, v = dr.select(hit, 0.0, m), dr.select(hit, 0.0, v)
        vmax = None if vmax is None else dr.select(hit, 0.0, vmax)
    dr.make_opaque(m, v)
    if vmax is not None:
        dr.make_opaque(vmax)
    opt.state[key] = (value, promoted, lr, (t, m, v, vmax))


def clear_grads(opt) -> None:
    """Zero the gradient of every registered parameter (values and Adam state untouched)."""
    for value, _, _, _ in opt.state.values():
        dr.clear_grad(value)


def replace_values(opt, key: str, value) -> None:
    """Overwrite ``key`` with a value of the SAME shape, keeping ``t`` and the moments (``Optimizer.__setitem__`` keeps
    the state for an unchanged shape). The new value is a fresh leaf: its gradient is zero."""
    old = opt.state[key][0]
    if tuple(value.shape) != tuple(old.shape):
        raise ValueError(f"replace_values: {key} has shape {tuple(old.shape)}, got {tuple(value.shape)} "
                         "(a new shape would reset the Adam state: use prune / append)")
    opt[key] = value


def moments(opt, key: str) -> tuple:
    """(t, m, v) of ``key`` as NumPy arrays shaped like the parameter (for tests and diagnostics; a host readback)."""
    value, _, _, (t, m, v, _) = opt.state[key]
    shape = tuple(value.shape)
    return int(np.array(t).reshape(-1)[0]), np.array(m).reshape(shape), np.array(v).reshape(shape)


# ---------------------------------------------------------------------------------------------- checkpoints
def export_state(opt) -> dict[str, np.ndarray]:
    """The Adam state of every registered parameter as NumPy arrays (for a checkpoint): ``<key>.t`` (uint32, shape
    (1,)), ``<key>.m`` and ``<key>.v`` (float32, the parameter's shape) and ``<key>.vmax`` when AMSGrad keeps one.
    Values and learning rates are not included (the parameters are saved with the model; rates come from the config
    and the schedule)."""
    out = {}
    for key, (value, _, _, (t, m, v, vmax)) in opt.state.items():
        shape = tuple(value.shape)
        out[f"{key}.t"] = np.array(t, dtype=np.uint32).reshape(1)
        out[f"{key}.m"] = np.array(m, dtype=np.float32).reshape(shape)
        out[f"{key}.v"] = np.array(v, dtype=np.float32).reshape(shape)
        if vmax is not None:
            out[f"{key}.vmax"] = np.array(vmax, dtype=np.float32).reshape(shape)
    return out


def import_state(opt, arrays: Mapping[str, np.ndarray]) -> None:
    """Restore what :func:`export_state` wrote into an optimizer whose parameters have the same shapes (e.g. one
    made by :func:`make_optimizer` from the checkpoint's parameters). Raises on a missing key or a shape mismatch."""
    for key in list(opt.state.keys()):
        value, promoted, lr, (t, m, v, vmax) = opt.state[key]
        shape = tuple(value.shape)
        flat_tp = type(m)

        def load(name):
            if name not in arrays:
                raise KeyError(f"import_state: {name!r} missing from the checkpoint")
            a = np.asarray(arrays[name], np.float32)
            if a.shape != shape:
                raise ValueError(f"import_state: {name} has shape {a.shape}, the parameter has {shape}")
            flat = _owned(flat_tp, a)
            dr.make_opaque(flat)
            return flat

        if f"{key}.t" not in arrays:
            raise KeyError(f"import_state: {key + '.t'!r} missing from the checkpoint")
        t_new = dr.opaque(type(t), int(np.asarray(arrays[f"{key}.t"]).reshape(-1)[0]), 1)
        m_new, v_new = load(f"{key}.m"), load(f"{key}.v")
        vmax_new = None
        if vmax is not None:
            vmax_new = load(f"{key}.vmax") if f"{key}.vmax" in arrays else dr.zeros(flat_tp, dr.width(vmax))
        opt.state[key] = (value, promoted, lr, (t_new, m_new, v_new, vmax_new))
