"""``GaussianAdam``: the one owner of the trainable Gaussians and their Adam state.

Mitsuba's ``mi.ad.Adam`` is ``drjit.opt.Adam``, which -- like every Dr.Jit optimizer -- owns the parameters it
optimizes: ``opt[key]`` is the grad-enabled value, ``opt.step()`` replaces it by a new one. ``GaussianAdam`` wraps one
such Adam over the six raw parameters of a :class:`~mi_gaussians.model.gaussians.Gaussians` model and is the only
place that holds them during training; :attr:`GaussianAdam.gaussians` is a view for rendering (its fields ARE the
optimizer's tensors, so ``dr.backward`` through a render fills the gradients ``step()`` uses).

Row operations. Densification adds and removes rows (Gaussians). Dr.Jit's ``opt[key] = value`` keeps a parameter's
state only when the shape is unchanged; a parameter of a NEW shape is re-registered with ``t = 0`` and zero moments,
which would throw away every Gaussian's Adam history and restart bias correction. 3DGS instead keeps the step count and
the moments of surviving rows and gives new rows zero moments. :meth:`~GaussianAdam.keep`,
:meth:`~GaussianAdam.append`, :meth:`~GaussianAdam.reset_moments` and :meth:`~GaussianAdam.replace` do that, each
through the one helper :meth:`~GaussianAdam._update` (as gsplat routes every change through
``_update_param_with_optimizer``). This module is the only one that reads or writes Dr.Jit 1.5's private state layout
(in ``_update``, and in the constructor, ``moments``, ``step``, ``export_moments`` and ``import_moments``)::

    adam.state[key] = (value, promoted, lr, (t, m, v, vmax))

(``value`` the grad-enabled parameter, ``promoted`` the fp16 -> fp32 flag, ``lr`` the parameter's learning rate, ``t``
the step count (a 1-element ``UInt32``), ``m`` and ``v`` the moments (flat arrays of the value's width) and ``vmax``
AMSGrad's running maximum or ``None``).

After a row change every parameter is a fresh AD leaf with a zero gradient, like the reference's freshly built
``nn.Parameter``s (whose ``.grad`` is None, so PyTorch's Adam skips them on that iteration). Gradients are deliberately
NOT carried over: a trainer that skips ``step()`` after a row change (as the reference effectively does) renders and
backpropagates into these same leaves next, and a carried gradient would be added to the next one. A trainer that
steps anyway gets a zero-gradient Adam step: rows with zero moments (new rows) stay exactly in place, kept rows coast
on their decayed momentum.

Frozen training steps. ``GaussianAdam`` is a Dr.Jit PyTree (``DRJIT_STRUCT``): a function frozen with ``dr.freeze``
can take it as an input, step it (:meth:`step` with an ``active`` flag and a learning rate held in a Dr.Jit value)
and the replays write the new tensors back into it (see :mod:`.train_step`).

SH degree 0: ``sh_rest`` is then an (N, 0, 3) tensor, and Dr.Jit refuses to register an empty parameter, so it is not
registered; the view gives an empty (N, 0, 3) tensor of the right N.

Typical loop (see :mod:`.trainer`)::

    params = GaussianAdam(g, cfg.optim, extent)
    state = strategy.initialize_state(params.n)
    for step in range(1, iterations + 1):
        params.set_learning_rate("means", schedule(step))
        out = render(params.gaussians, cam)
        strategy.step_pre_backward(params, state, step, out)
        dr.backward(loss(out))
        info = strategy.step_post_backward(params, state, step, out)   # row changes through params
        if not info.changed:
            params.step()
"""

from __future__ import annotations

from typing import Callable, Mapping

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import OptimConfig
from ..drjit_utils import concat, owned_array
from ..model.gaussians import PARAMETER_NAMES, Gaussians


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


# ------------------------------------------------------------------------------------------ flat row arithmetic
def row_index(rows, n: int) -> "mi.UInt32":
    """A ``UInt32`` index array from a boolean mask of length n (NumPy or Dr.Jit) or from row indices."""
    if isinstance(rows, (list, tuple)):
        rows = np.asarray(rows)
    if isinstance(rows, np.ndarray):
        if rows.dtype == np.bool_:
            if rows.shape != (n,):
                raise ValueError(f"row mask of shape {rows.shape}, expected ({n},)")
            return owned_array(mi.UInt32, np.flatnonzero(rows).astype(np.uint32))
        idx = np.asarray(rows, np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise IndexError(f"row index out of range 0..{n - 1}")
        return owned_array(mi.UInt32, idx.astype(np.uint32))
    if dr.is_array_v(rows) and dr.type_v(rows) == dr.VarType.Bool:
        if dr.width(rows) != n:
            raise ValueError(f"row mask of width {dr.width(rows)}, expected {n}")
        return dr.compress(rows)
    if dr.is_array_v(rows) and dr.is_integral_v(rows):
        return mi.UInt32(rows)
    raise TypeError(f"rows must be a boolean mask or an index array, got {type(rows).__name__}")


def flat_index(rows: "mi.UInt32", row_size: int) -> "mi.UInt32":
    """Flat element indices of ``rows`` in a row-major (N, row_size) array: row r -> r*row_size + [0, row_size)."""
    if row_size == 1 or dr.width(rows) == 0:    # (Dr.Jit arithmetic refuses to mix a width-0 and a literal)
        return rows
    return dr.repeat(rows * row_size, row_size) + dr.tile(dr.arange(mi.UInt32, row_size), dr.width(rows))


def gather_rows(flat, rows: "mi.UInt32", row_size: int):
    """Rows ``rows`` of a flat row-major array (a detached, lazily evaluated gather)."""
    return dr.gather(type(flat), dr.detach(flat), flat_index(rows, row_size))


def _row_size(shape: tuple) -> int:
    return int(np.prod(shape[1:])) if len(shape) > 1 else 1


def _as_flat(x, flat_tp) -> tuple:
    """(flat Dr.Jit array of ``flat_tp``, shape) of a NumPy array or a Dr.Jit tensor."""
    if isinstance(x, (np.ndarray, list, tuple)):
        a = np.ascontiguousarray(x, dtype=np.float32)
        return owned_array(flat_tp, a), a.shape
    if dr.is_tensor_v(x):
        return flat_tp(dr.detach(x).array), tuple(x.shape)
    raise TypeError(f"new rows must be NumPy arrays or Dr.Jit tensors, got {type(x).__name__}")


# A row change: (key, flat array, row size) -> new flat array, for the value and for each moment.
RowFn = Callable[[str, object, int], object]


class GaussianAdam:
    """Adam (``mi.ad.Adam``, eps ``cfg.adam_eps``, betas 0.9 / 0.999) owning the six raw parameters of a model.

    ``g``'s values are copied in; ``g`` is not kept. Every registered parameter has its own learning rate
    (:func:`learning_rates`); the global rate is 0, so nothing moves at a guessed rate."""

    # a PyTree for dr.freeze: the wrapped optimizer (itself a DRJIT_STRUCT of its rates and state) is traversed
    DRJIT_STRUCT = {"_adam": object}

    def __init__(self, g: Gaussians, cfg: OptimConfig, extent: float):
        if g.n == 0:
            raise ValueError("the model has no Gaussians (Dr.Jit refuses empty parameters)")
        self._adam = mi.ad.Adam(lr=0.0, epsilon=float(cfg.adam_eps))
        self._rest_coeffs = int(g.sh_rest.shape[1])      # K - 1: fixed for a run
        for key in PARAMETER_NAMES:
            value = getattr(g, key)
            if dr.width(value) != 0:                    # (sh_rest of degree 0 is empty)
                self._adam[key] = value
        rates = learning_rates(cfg, extent)
        self._adam.set_learning_rate({k: rates[k] for k in self.keys()})
        opaque_step_counts(self._adam, self.keys())

    # ------------------------------------------------------------------ reading
    @property
    def n(self) -> int:
        """Number of Gaussians (rows)."""
        return int(self._adam["means"].shape[0])

    def keys(self) -> list[str]:
        """The registered parameters (``sh_rest`` only for an SH degree above 0), in :data:`PARAMETER_NAMES` order."""
        return [k for k in PARAMETER_NAMES if k in self._adam]

    def __contains__(self, key: str) -> bool:
        return key in self._adam

    def __getitem__(self, key: str) -> "mi.TensorXf":
        """The current (grad-enabled) tensor of ``key``; ``sh_rest`` of degree 0 is an empty (N, 0, 3) tensor."""
        if key in self._adam:
            return self._adam[key]
        if key != "sh_rest":
            raise KeyError(key)
        return mi.TensorXf(dr.zeros(mi.Float, 0), (self.n, self._rest_coeffs, 3))

    @property
    def gaussians(self) -> Gaussians:
        """A view for rendering: a ``Gaussians`` whose fields are the current tensors. Take a new one after
        :meth:`step` or a row change (both replace the tensors)."""
        return Gaussians(**{key: self[key] for key in PARAMETER_NAMES})

    def learning_rate(self, key: str) -> float | None:
        """The rate of ``key`` as a float (a rate held in a Dr.Jit value is read back)."""
        lr = self._adam.learning_rate(key)
        return float(lr[0]) if dr.is_array_v(lr) else lr

    def set_learning_rate(self, key: str, lr) -> None:
        """A Python float (Dr.Jit passes it to the update kernel as an opaque value: no recompilation), or a 1-element
        ``mi.Float`` (inside a frozen step, where a Python float would be part of the recording's key)."""
        self._adam.set_learning_rate({key: lr if dr.is_array_v(lr) else float(lr)})

    @property
    def epsilon(self) -> float:
        return float(self._adam.epsilon)

    @property
    def betas(self) -> tuple[float, float]:
        return float(self._adam.beta_1), float(self._adam.beta_2)

    def moments(self, key: str) -> tuple[int, np.ndarray, np.ndarray]:
        """(t, m, v) of ``key`` as NumPy arrays shaped like the parameter (a host readback)."""
        value, _, _, (t, m, v, _) = self._adam.state[key]
        shape = tuple(value.shape)
        return int(np.array(t).reshape(-1)[0]), np.array(m).reshape(shape), np.array(v).reshape(shape)

    # ------------------------------------------------------------------ optimizing
    def step(self, active=None) -> None:
        """One Adam step of every parameter from its gradient (``dr.backward`` through a render of the view).

        ``active``: a 1-element ``mi.Bool``; where it is False nothing changes -- values, moments AND the step count
        ``t`` (Dr.Jit's own ``active`` leaves ``t`` counting, a known issue it documents), so a masked step is no step.
        """
        masked_step(self._adam, self.keys(), active)

    def clear_grads(self) -> None:
        """Zero the gradient of every parameter (values and Adam state untouched)."""
        for key in self.keys():
            dr.clear_grad(self._adam[key])

    # ------------------------------------------------------------------ row operations
    def rows(self, rows) -> dict[str, "mi.TensorXf"]:
        """Detached copies of the rows ``rows`` (boolean mask or indices) of every registered parameter."""
        idx = row_index(rows, self.n)
        out = {}
        for key in self.keys():
            value = self._adam[key]
            shape = (dr.width(idx),) + tuple(value.shape[1:])
            out[key] = mi.TensorXf(gather_rows(value.array, idx, _row_size(tuple(value.shape))), shape)
        return out

    def keep(self, rows) -> None:
        """Keep the rows ``rows`` (boolean mask of length N, NumPy or ``mi.Bool``; or row indices) of every parameter
        and of its moments, in that order. ``t`` and the learning rates are kept. Removing every row raises (Dr.Jit
        refuses empty parameters)."""
        idx = row_index(rows, self.n)
        if dr.width(idx) == 0:
            raise RuntimeError("keeping no row would remove every Gaussian (Dr.Jit refuses empty parameters)")

        def take(key, flat, row_size):
            return gather_rows(flat, idx, row_size)

        self._update(take, take)

    def append(self, new_rows: Mapping[str, object]) -> None:
        """Concatenate ``new_rows[key]`` (shape (k, *row_shape), NumPy or ``TensorXf``) after the rows of every
        parameter. Every registered parameter must be given, with the same k. New rows get zero moments; kept rows
        keep theirs; ``t`` and the learning rates are kept. ``sh_rest`` of degree 0 is accepted only when empty."""
        unknown = [k for k in new_rows if k not in PARAMETER_NAMES]
        if unknown:
            raise KeyError(f"append: unknown parameter(s) {unknown}")
        for key in new_rows:
            if key not in self and dr.width(_as_flat(new_rows[key], mi.Float)[0]) != 0:
                raise KeyError(f"append: parameter {key!r} is not registered but its new rows are not empty")
        missing = [k for k in self.keys() if k not in new_rows]
        if missing:
            raise KeyError(f"append: new rows missing for {missing}")
        flats, counts = {}, set()
        for key in self.keys():
            flat, shape = _as_flat(new_rows[key], mi.Float)
            expect = tuple(self._adam[key].shape[1:])
            if tuple(shape[1:]) != expect:
                raise ValueError(f"append: {key} rows of shape {tuple(shape[1:])}, expected {expect}")
            flats[key] = flat
            counts.add(shape[0])
        if len(counts) != 1:
            raise ValueError(f"append: the parameters have different numbers of new rows ({sorted(counts)})")
        if counts == {0}:
            return

        def values(key, flat, row_size):
            return concat([dr.detach(flat), flats[key]])

        def moments(key, flat, row_size):
            return concat([flat, dr.zeros(type(flat), dr.width(flats[key]))])

        self._update(values, moments)

    def set_rows(self, rows, values: Mapping[str, object]) -> None:
        """Overwrite the rows ``rows`` (indices; repeated indices must carry equal values) of the parameters in
        ``values`` (key -> (len(rows), *row_shape), NumPy or ``TensorXf``) and zero the moments of those rows of
        EVERY parameter: they are new Gaussians (MCMC relocation). Other rows, ``t`` and the rates are kept."""
        unknown = [k for k in values if k not in self]
        if unknown:
            raise KeyError(f"set_rows: unknown parameter(s) {unknown}")
        idx = row_index(rows, self.n)
        k = dr.width(idx)
        if k == 0:
            return
        flats = {}
        for key, new in values.items():
            flat, shape = _as_flat(new, mi.Float)
            expect = (k,) + tuple(self._adam[key].shape[1:])
            if tuple(shape) != expect:
                raise ValueError(f"set_rows: {key} rows of shape {tuple(shape)}, expected {expect}")
            flats[key] = flat

        def write(zero_rows: bool):
            def fn(key, flat, row_size):
                out = dr.copy(dr.detach(flat))              # the scatter must not reach the old array
                dr.scatter(out, 0.0 if zero_rows else flats[key], flat_index(idx, row_size))
                return out
            return fn

        self._update(write(False), write(True), keys=list(flats))
        rest = [key for key in self.keys() if key not in flats]
        if rest:
            self._update(None, write(True), keys=rest)

    def reset_moments(self, key: str, rows=None) -> None:
        """Zero the moments (and ``vmax``) of ``key``, for all rows or for ``rows`` (boolean mask or indices).
        ``t``, the value and its gradient are untouched (3DGS's opacity reset)."""
        if rows is None:
            def zero(k, flat, row_size):
                return dr.zeros(type(flat), dr.width(flat))
        else:
            idx = flat_index(row_index(rows, self.n), _row_size(tuple(self._adam[key].shape)))

            def zero(k, flat, row_size):
                hit = dr.zeros(dr.mask_t(type(flat)), dr.width(flat))   # a fresh array: scattering into it is safe
                dr.scatter(hit, True, idx)
                return dr.select(hit, 0.0, flat)

        self._update(None, zero, keys=[key])

    def replace(self, key: str, value: "mi.TensorXf") -> None:
        """Overwrite ``key`` with a value of the SAME shape, keeping ``t`` and the moments. The new value is a fresh
        leaf: its gradient is zero."""
        old = self._adam[key]
        if tuple(value.shape) != tuple(old.shape):
            raise ValueError(f"replace: {key} has shape {tuple(old.shape)}, got {tuple(value.shape)} "
                             "(rows change only through keep / append)")
        self._update(lambda k, flat, rs: dr.detach(value).array, None, keys=[key])

    def _update(self, value_fn: RowFn | None, moment_fn: RowFn | None, keys=None) -> None:
        """THE row-change helper: new values (``value_fn``) and moments (``moment_fn``, applied to m, v and vmax) of
        ``keys`` (default all), each a fresh, opaque leaf; the new number of rows follows from the new widths.
        ``None`` keeps the value / the moments. ``t``, ``promoted`` and the learning rate are kept."""
        for key in self.keys() if keys is None else keys:
            value, promoted, lr, (t, m, v, vmax) = self._adam.state[key]
            shape = tuple(value.shape)
            rs = _row_size(shape)
            flat = value.array if value_fn is None else value_fn(key, value.array, rs)
            if moment_fn is not None:
                m, v = moment_fn(key, m, rs), moment_fn(key, v, rs)
                vmax = None if vmax is None else moment_fn(key, vmax, rs)
            if dr.width(flat) == 0:
                raise RuntimeError("a row change would leave a parameter empty (Dr.Jit refuses empty parameters)")
            if value_fn is None:
                new = value
            else:
                new = dr.detach(type(value)(flat, (dr.width(flat) // rs,) + shape[1:]))
                dr.make_opaque(new)
                dr.enable_grad(new)
            dr.make_opaque(m, v)
            if vmax is not None:
                dr.make_opaque(vmax)
            self._adam.state[key] = (new, promoted, lr, (t, m, v, vmax))
        n = {int(self._adam.state[k][0].shape[0]) for k in self.keys()}
        if len(n) != 1:
            raise RuntimeError(f"a row change left the parameters with different numbers of rows {sorted(n)}")

    # ------------------------------------------------------------------ checkpoints
    def finite(self) -> dict[str, "mi.Bool"]:
        """Per parameter, whether its values and Adam moments are all finite (1-element device flags)."""
        return finite_state(self._adam, self.keys())

    def export_moments(self) -> dict[str, np.ndarray]:
        """The Adam state as NumPy arrays (for a checkpoint): ``<key>.t`` (uint32, shape (1,)), ``<key>.m`` and
        ``<key>.v`` (float32, the parameter's shape) and ``<key>.vmax`` when AMSGrad keeps one. Values and learning
        rates are not included (the model is saved with :attr:`gaussians`; rates come from the config)."""
        return export_state(self._adam, self.keys())

    def import_moments(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Restore what :meth:`export_moments` wrote, for parameters of the same shapes. Raises KeyError on a
        missing entry and ValueError on a shape mismatch, before changing anything."""
        import_state(self._adam, self.keys(), arrays)


# ------------------------------------------------------------------ the optimizer state, for every owner of parameters
def opaque_step_counts(adam, keys) -> None:
    """Dr.Jit registers a parameter's step count ``t`` as the literal 0, and literal + 1 stays a literal: the bias
    correction would be a new constant in some kernel on every step (a recompilation), and a literal input of a
    frozen step. Make each an opaque value."""
    for key in keys:
        value, promoted, lr, (t, m, v, vmax) = adam.state[key]
        adam.state[key] = (value, promoted, lr, (dr.opaque(type(t), 0, 1), m, v, vmax))


def masked_step(adam, keys, active=None) -> None:
    """``adam.step()`` where the 1-element ``mi.Bool`` ``active`` leaves everything as it was when False -- values,
    moments AND the step count ``t`` (Dr.Jit's own ``active`` leaves ``t`` counting, a known issue it documents)."""
    before = {key: adam.state[key] for key in keys}
    for key, (value, promoted, lr, extra) in before.items():
        if dr.is_array_v(lr):
            # Dr.Jit's learning-rate cache multiplies a rate held in an array in place (``scale *= factor``): give it
            # a copy, so the rate we hold stays the rate that was set
            adam.state[key] = (value, promoted, type(lr)(lr), extra)
    adam.step(active=active, eval=False)
    for key, (_, _, lr, (t_old, _, _, _)) in before.items():
        value, promoted, _, (t, m, v, vmax) = adam.state[key]
        if active is not None:
            t = dr.select(active, t, t_old)
            dr.schedule(t)
        adam.state[key] = (value, promoted, lr, (t, m, v, vmax))
    dr.eval()


def finite_state(adam, keys) -> dict[str, "mi.Bool"]:
    """Per key, a 1-element device ``mi.Bool``: whether its values and Adam moments are all finite (nothing is read
    back here; the caller reads the flags with its next synchronization)."""
    out = {}
    for key in keys:
        value, _, _, (_, m, v, vmax) = adam.state[key]
        ok = dr.all(dr.isfinite(dr.detach(value).array)) & dr.all(dr.isfinite(m)) & dr.all(dr.isfinite(v))
        if vmax is not None:
            ok = ok & dr.all(dr.isfinite(vmax))
        out[key] = ok
    return out


def export_state(adam, keys) -> dict[str, np.ndarray]:
    """The Adam state of ``keys`` as NumPy arrays: ``<key>.t`` (uint32, (1,)), ``<key>.m``, ``<key>.v`` (float32, the
    parameter's shape) and ``<key>.vmax`` when AMSGrad keeps one."""
    out = {}
    for key in keys:
        value, _, _, (t, m, v, vmax) = adam.state[key]
        shape = tuple(value.shape)
        out[f"{key}.t"] = np.array(t, dtype=np.uint32).reshape(1)
        out[f"{key}.m"] = np.array(m, dtype=np.float32).reshape(shape)
        out[f"{key}.v"] = np.array(v, dtype=np.float32).reshape(shape)
        if vmax is not None:
            out[f"{key}.vmax"] = np.array(vmax, dtype=np.float32).reshape(shape)
    return out


def import_state(adam, keys, arrays: Mapping[str, np.ndarray]) -> None:
    """Restore what :func:`export_state` wrote, for parameters of the same shapes. Raises KeyError on a missing entry
    and ValueError on a shape mismatch, before changing anything."""
    new = {}
    for key in keys:
        value, _, _, (t, _, _, vmax) = adam.state[key]
        shape = tuple(value.shape)

        def load(name):
            if name not in arrays:
                raise KeyError(f"{name!r} missing from the saved Adam state")
            a = np.asarray(arrays[name], np.float32)
            if a.shape != shape:
                raise ValueError(f"saved Adam state {name} has shape {a.shape}, the parameter has {shape}")
            return owned_array(mi.Float, a)

        if f"{key}.t" not in arrays:
            raise KeyError(f"{key + '.t'!r} missing from the saved Adam state")
        t_new = dr.opaque(type(t), int(np.asarray(arrays[f"{key}.t"]).reshape(-1)[0]), 1)
        m, v = load(f"{key}.m"), load(f"{key}.v")
        if vmax is not None:
            vmax = load(f"{key}.vmax") if f"{key}.vmax" in arrays else dr.zeros(mi.Float, dr.width(m))
        new[key] = (t_new, m, v, vmax)
    for key, (t_new, m, v, vmax) in new.items():
        value, promoted, lr, _ = adam.state[key]
        dr.make_opaque(m, v)
        adam.state[key] = (value, promoted, lr, (t_new, m, v, vmax))
