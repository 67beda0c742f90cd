"""Adaptive density control of 3DGS (clone, split, prune, opacity reset) as a gsplat-style strategy.

    strategy = DefaultStrategy(cfg.densify, extent, seed=0)
    for step in range(1, iterations + 1):          # 1-based, like the reference's ``iteration``
        out = render(g, cam); dr.backward(loss)
        info = strategy.step_post_backward(step, g, opt, out, W, H, white_background=...)
        if not info["changed"]:
            opt.step()                             # see "Calling order" below
        sync_gaussians(opt, g)

The strategy only reads ``out.radii`` (``Int32`` (N,), 0 = not visible) and ``out.means2d_grad`` (``Vector2f`` (N,),
dL/d(projected mean) in pixels) from the render output, and reads/changes the parameters through the optimizer
(``opt`` is the source of truth; every row change goes through :mod:`.optimizer`, which carries the Adam moments, and
``g`` is re-synchronized at the end).

Rules (the reference ``train.py`` / ``densify_and_prune``; ``step`` is the 1-based iteration)::

    while step < densify_until_iter:
        statistics, for Gaussians with radii > 0:
            grad_accum += |(gx W/2, gy H/2)|     (pixel gradient in NDC units, as the reference CUDA rasterizer reports it)
            denom += 1;  max_radii = max(max_radii, radii)
        if step > densify_from_iter and step % densification_interval == 0:
            grad = grad_accum / denom (0 where denom == 0)
            clone: grad >= threshold and max(exp(scales)) <= percent_dense * extent      (exact copies)
            split: grad >= threshold and max(exp(scales)) >  percent_dense * extent      (clones are not candidates)
                   split_count children, mean x + R(q) (sigma * n), n ~ N(0, I), scale log(sigma / split_scale_divisor),
                   other parameters copied; the original is removed
            prune: sigmoid(opacity) < min_opacity, and when step > opacity_reset_interval also
                   max_radii > max_screen_size or max(exp(scales)) > max_world_scale * extent
            statistics reset to zero (all remaining rows)
        if step % opacity_reset_interval == 0 or (white_background and step == densify_from_iter):
            opacity = logit(min(sigmoid(opacity), reset_opacity)); opacity's Adam moments zeroed

Row order is the reference's: [originals that were neither split nor pruned, clones, children (copy-major: first child
of every split Gaussian, then the second ...)], each minus the pruned ones. The reference appends clones, appends
children, removes the split originals, then prunes; we append clones and children in one call and remove split
originals and pruned rows in one call (same result, two state rewrites instead of four).

Deliberate differences from the reference code (each flagged where it is implemented):

* Screen-size pruning is live. The reference's ``densification_postfix`` zeroes ``max_radii2D`` before its prune
  test, so its ``max_radii2D > 20`` test never fires (only the world-size test does); we apply the rule as documented
  in ``conventions.md``: new rows inherit their source's ``max_radii`` (as gsplat does) and the test uses them. Set
  ``DensifyConfig.max_screen_size = float("inf")`` to reproduce the reference's effective behaviour.
* The opacity reset keeps a logit unchanged when its opacity is already below ``reset_opacity`` (the reference round
  trips it through sigmoid and logit: equal up to float rounding, except that very negative logits would become -inf).
* ``densify_until_iter`` bounds everything with ``step < densify_until_iter`` exactly as the reference's
  ``if iteration < opt.densify_until_iter`` block (so no opacity reset at step 15000 with the defaults).

Calling order. PyTorch's Adam skips parameters whose ``.grad`` is None, which is what the reference's freshly rebuilt
parameters are after a densification (all six) or an opacity reset (opacity), so its optimizer step is skipped on
those iterations; the ``changed`` flag of the returned info lets the trainer do the same. Every rewritten parameter is
a fresh Dr.Jit leaf with zero gradient (gradients are not carried: see :mod:`.optimizer`). A trainer that steps anyway
leaves new rows and reset opacities exactly in place (zero gradient, zero moments); kept rows would coast on their
decayed momentum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import DensifyConfig
from ..model.gaussians import Gaussians
from ..raster.mathops import fmax
from . import optimizer as ostate


@dataclass
class DensifyState:
    """Running statistics per Gaussian (Dr.Jit arrays, width N).

    Kept in Dr.Jit rather than NumPy: the per-iteration update is three element-wise selects on arrays the renderer
    already holds on the device; in Dr.Jit they are scheduled and fused into the next kernel launch with no host
    synchronization, while NumPy would force a readback of ``radii`` and ``means2d_grad`` every iteration."""

    grad_accum: "mi.Float"      # sum of NDC-space |dL/d mean2d| over the iterations where the Gaussian was visible
    denom: "mi.Float"           # number of those iterations
    max_radii: "mi.Int32"       # largest screen radius (px) seen

    @property
    def n(self) -> int:
        return dr.width(self.grad_accum)

    def numpy(self) -> dict[str, np.ndarray]:
        return {"grad_accum": np.array(self.grad_accum, dtype=np.float32),
                "denom": np.array(self.denom, dtype=np.float32),
                "max_radii": np.array(self.max_radii, dtype=np.int32)}


def _sigmoid(x):
    return dr.rcp(1.0 + dr.exp(-x))


def _rows3(t) -> "mi.Vector3f":
    """An (N, 3) tensor's rows as a detached ``Vector3f``."""
    return dr.unravel(mi.Vector3f, dr.detach(t).array)


def _max3(v):
    return fmax(fmax(v.x, v.y), v.z)


def _rotation(q_flat) -> "mi.Matrix3f":
    """Rotation matrices of (w, x, y, z) quaternions given as a flat (N*4) array (normalized here, like the
    reference's ``build_rotation``)."""
    q = dr.unravel(mi.Vector4f, q_flat)
    q = q * dr.rsqrt(fmax(dr.squared_norm(q), 1e-24))
    w, x, y, z = q.x, q.y, q.z, q.w
    return mi.Matrix3f(
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


class DefaultStrategy:
    """The reference 3DGS densification (see the module docstring). ``extent``: the scene extent (``Dataset.extent``).

    Holds the running statistics (``self.state``, a :class:`DensifyState` made on the first call) and the random
    stream of the split samples (seeded by ``seed``; each densification draws from a new, counted stream so a resumed
    run draws the same samples)."""

    def __init__(self, cfg: DensifyConfig, extent: float, seed: int = 0):
        if cfg.split_count < 1:
            raise ValueError("split_count must be >= 1")
        self.cfg = cfg
        self.extent = float(extent)
        self.seed = int(seed)
        self.draws = 0                       # densifications that drew split samples (the random stream's counter)
        self.state: DensifyState | None = None

    # ------------------------------------------------------------------ state
    @staticmethod
    def initial_state(n: int) -> DensifyState:
        return DensifyState(grad_accum=dr.zeros(mi.Float, n), denom=dr.zeros(mi.Float, n),
                            max_radii=dr.zeros(mi.Int32, n))

    def _state_for(self, n: int) -> DensifyState:
        if self.state is None:
            self.state = self.initial_state(n)
        elif self.state.n != n:
            raise ValueError(f"densification statistics cover {self.state.n} Gaussians but the model has {n}: "
                             "change rows only through the strategy (or reset it with strategy.state = None)")
        return self.state

    def export_state(self) -> dict[str, np.ndarray]:
        """The statistics as NumPy arrays (for a checkpoint); empty before the first call."""
        return {} if self.state is None else self.state.numpy()

    def export_meta(self) -> dict:
        return {"seed": self.seed, "draws": self.draws}

    def import_state(self, arrays: dict, meta: dict | None = None) -> None:
        if arrays:
            n = len(arrays["grad_accum"])
            if len(arrays["denom"]) != n or len(arrays["max_radii"]) != n:
                raise ValueError("densification statistics of different lengths")
            self.state = DensifyState(
                grad_accum=ostate._owned(mi.Float, np.asarray(arrays["grad_accum"], np.float32)),
                denom=ostate._owned(mi.Float, np.asarray(arrays["denom"], np.float32)),
                max_radii=ostate._owned(mi.Int32, np.asarray(arrays["max_radii"], np.int32)))
            dr.eval(self.state.grad_accum, self.state.denom, self.state.max_radii)
        else:
            self.state = None
        if meta:
            self.seed = int(meta.get("seed", self.seed))
            self.draws = int(meta.get("draws", 0))

    # ------------------------------------------------------------------ hooks
    def step_pre_backward(self, *args, **kwargs) -> None:
        """No-op. gsplat uses this hook to ask for the gradient of the projected means; our rasterizer always
        records it (``RenderOutput.means2d_grad``), so there is nothing to do before the backward pass."""
        return None

    def step_post_backward(self, step: int, g: Gaussians, opt, out, width: int, height: int,
                           white_background: bool = False) -> dict:
        """Update the statistics and, on the scheduled iterations, densify / prune / reset opacities.

        Returns ``{"cloned", "split", "pruned", "reset", "densified", "opacity_reset", "changed", "n"}``:
        counts of Gaussians cloned, split (originals), pruned (by the prune tests), opacities lowered by the reset;
        whether a densification / opacity reset ran; ``changed``: either ran, so the reference's Adam step would skip
        its rebuilt parameters: every parameter's gradient has been cleared and the trainer should skip
        ``opt.step()``; ``n``: the number of Gaussians afterwards. Counts are read back only on those iterations."""
        cfg = self.cfg
        n = ostate._num_rows(opt)
        info = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0, "densified": False, "opacity_reset": False,
                "changed": False, "n": n}
        if step >= cfg.densify_until_iter:
            return info
        st = self._state_for(n)
        self._accumulate(st, out, width, height)

        if step > cfg.densify_from_iter and step % cfg.densification_interval == 0:
            info.update(self._densify_and_prune(step, opt))
            info["densified"] = info["changed"] = True
        if step % cfg.opacity_reset_interval == 0 or (white_background and step == cfg.densify_from_iter):
            info["reset"] = self._reset_opacity(opt)
            info["opacity_reset"] = info["changed"] = True
        if info["changed"]:
            # The reference rebuilds every parameter on a densification iteration (and opacity on a reset), so they
            # have no gradient and its Adam step skips them. Rows that were not rewritten here still hold this
            # iteration's gradient: clear it, or a trainer that skips the step would add it to the next backward pass.
            ostate.clear_grads(opt)
            ostate.sync_gaussians(opt, g)
            info["n"] = ostate._num_rows(opt)
        return info

    # ------------------------------------------------------------------ pieces
    def _accumulate(self, st: DensifyState, out, width: int, height: int) -> None:
        radii = out.radii
        if dr.width(radii) != st.n:
            raise ValueError(f"render output has {dr.width(radii)} Gaussians, the statistics {st.n}")
        grad = dr.detach(out.means2d_grad)
        # the reference rasterizer reports dL/d(mean2d) in NDC units: pixel gradient times W/2 and H/2
        gx = grad.x * dr.opaque(mi.Float, 0.5 * float(width))
        gy = grad.y * dr.opaque(mi.Float, 0.5 * float(height))
        visible = radii > 0
        st.grad_accum = dr.select(visible, st.grad_accum + dr.sqrt(dr.fma(gx, gx, gy * gy)), st.grad_accum)
        st.denom = dr.select(visible, st.denom + 1.0, st.denom)
        st.max_radii = dr.select(visible & (radii > st.max_radii), radii, st.max_radii)
        # evaluated with the next kernel launch (the optimizer step's dr.eval), without a sync here
        dr.schedule(st.grad_accum, st.denom, st.max_radii)

    def _split_normals(self, m: int) -> "mi.Vector3f":
        """m standard-normal 3-vectors from this strategy's counted random stream."""
        state = ((self.seed & 0xFFFFFFFF) << 32) | (self.draws & 0xFFFFFFFF)
        self.draws += 1
        rng = mi.PCG32(size=m, initstate=dr.opaque(mi.UInt64, state), initseq=dr.arange(mi.UInt64, m))
        u = [rng.next_float32() for _ in range(4)]
        a = mi.warp.square_to_std_normal(mi.Point2f(u[0], u[1]))
        b = mi.warp.square_to_std_normal(mi.Point2f(u[2], u[3]))
        return mi.Vector3f(a.x, a.y, b.x)

    def _densify_and_prune(self, step: int, opt) -> dict:
        cfg, st = self.cfg, self.state
        n = st.n
        dense = float(cfg.percent_dense) * self.extent
        sigma_max = _max3(dr.exp(_rows3(opt["scales"])))
        grads = dr.select(st.denom > 0, st.grad_accum / st.denom, 0.0)
        high = grads >= float(cfg.grad_threshold)
        clone_idx = dr.compress(high & (sigma_max <= dense))
        split_mask = high & (sigma_max > dense)
        split_idx = dr.compress(split_mask)
        n_clone, n_split = dr.width(clone_idx), dr.width(split_idx)
        k = int(cfg.split_count)

        # ---- new rows: clones (exact copies), then the children of the split Gaussians, copy-major like torch's
        # .repeat(k, 1) in the reference
        child_src = dr.tile(split_idx, k) if n_split else split_idx   # (dr.tile fails on width 0)
        src = ostate.concat([clone_idx, child_src])
        max_radii = st.max_radii
        if dr.width(src):
            new_rows = {}
            for key, (value, _, _, _) in opt.state.items():
                rs = ostate._row_size(value)
                flat = ostate._gather_rows(value.array, src, rs)
                new_rows[key] = type(value)(flat, (dr.width(src),) + tuple(value.shape[1:]))
            if n_split:
                m = n_split * k
                means_c = dr.gather(mi.Vector3f, dr.detach(opt["means"].array), child_src)
                scales_c = dr.gather(mi.Vector3f, dr.detach(opt["scales"].array), child_src)
                quats_c = dr.gather(mi.Float, dr.detach(opt["rotations"].array), ostate._flat_index(child_src, 4))
                sigma_c = dr.exp(scales_c)
                child_means = means_c + _rotation(quats_c) @ (sigma_c * self._split_normals(m))
                child_scales = dr.log(sigma_c / float(cfg.split_scale_divisor))
                for key, vals in (("means", child_means), ("scales", child_scales)):
                    head = ostate._gather_rows(opt[key].array, clone_idx, 3)
                    new_rows[key] = mi.TensorXf(ostate.concat([head, dr.ravel(vals)]), (n_clone + m, 3))
            ostate.append(opt, new_rows)
            max_radii = ostate.concat([max_radii, dr.gather(mi.Int32, max_radii, src)])

        # ---- prune (over every row, new ones included, as the reference) and remove the split originals
        n_all = n + dr.width(src)
        prune = _sigmoid(dr.detach(opt["opacities"].array)) < float(cfg.min_opacity)
        if step > cfg.opacity_reset_interval:
            big_screen = mi.Float(max_radii) > float(cfg.max_screen_size)   # dead code in the reference (see top)
            big_world = _max3(dr.exp(_rows3(opt["scales"]))) > float(cfg.max_world_scale) * self.extent
            prune = prune | big_screen | big_world
        is_split = ostate.concat([split_mask, dr.zeros(mi.Bool, n_all - n)])
        remove = prune | is_split
        n_pruned = dr.count(prune & ~is_split)
        n_pruned = int(n_pruned[0]) if dr.is_array_v(n_pruned) else int(n_pruned)
        if n_pruned or n_split:
            ostate.prune(opt, ~remove)

        self.state = self.initial_state(ostate._num_rows(opt))
        return {"cloned": n_clone, "split": n_split, "pruned": n_pruned}

    def _reset_opacity(self, opt) -> int:
        """opacity = min(opacity, reset_opacity) in logit space, opacity's Adam moments zeroed; returns how many
        Gaussians were lowered."""
        r = float(self.cfg.reset_opacity)
        o = dr.detach(opt["opacities"])
        lower = _sigmoid(o.array) >= r
        # Logits already below stay bit-identical (the reference's sigmoid/logit round trip differs by rounding only)
        new = dr.select(lower, math.log(r / (1.0 - r)), o.array)
        ostate.replace_values(opt, "opacities", mi.TensorXf(new, tuple(o.shape)))
        ostate.reset_moments(opt, "opacities")
        dr.eval(opt.state["opacities"])
        cnt = dr.count(lower)
        return int(cnt[0]) if dr.is_array_v(cnt) else int(cnt)
