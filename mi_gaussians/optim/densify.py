"""Adaptive density control of 3DGS (clone, split, prune, opacity reset) as a gsplat-style strategy.

    strategy = DefaultStrategy(cfg.densify, extent, seed=0, white_background=...)
    state = strategy.initialize_state(params.n)    # the caller owns the state (and checkpoints it)
    for step in range(1, iterations + 1):          # 1-based, like the reference's ``iteration``
        out = render(params.gaussians, cam); dr.backward(loss)
        info = strategy.step_post_backward(params, state, step, out)
        if not info.changed:
            params.step()                          # see "Calling order" below

The strategy implements :class:`~.strategy.Strategy`. It only reads ``out.radii`` (``Int32`` (N,), 0 = not visible),
``out.means2d_grad`` (``Vector2f`` (N,), dL/d(projected mean) in pixels) and the image size from the render output,
and reads and changes the parameters through their owner ``params`` (:class:`~.adam.GaussianAdam`), whose row
operations carry the Adam moments.

Rules (the reference ``train.py`` / ``densify_and_prune``; ``step`` is the 1-based iteration)::

    while step < densify_until_iter:
        statistics, for Gaussians with radii > 0:
            grad_accum += |(gx W/2, gy H/2)|     (pixel gradient in NDC units, as the reference CUDA rasterizer reports it;
                                                  with absgrad (AbsGS, gsplat) g is the sum over pixels of |each
                                                  pixel's contribution|, per axis, and the threshold absgrad_threshold)
            denom += 1;  max_screen = max(max_screen, radii / max(W, H))
        if step > densify_from_iter and step % densification_interval == 0:
            grad = grad_accum / denom (0 where denom == 0)
            clone: grad >= threshold and max(exp(scales)) <= percent_dense * extent      (exact copies)
            split: grad >= threshold and max(exp(scales)) >  percent_dense * extent      (clones are not candidates)
                   split_count children, mean x + R(q) (sigma * n), n ~ N(0, I), scale log(sigma / split_scale_divisor),
                   other parameters copied; the original is removed
            prune: sigmoid(opacity) < min_opacity, and when step > prune_large_after also
                   max(exp(scales)) > max_world_scale * extent, or (when max_screen_fraction > 0, and while
                   step <= prune_large_after + screen_prune_span when that is > 0) max_screen > max_screen_fraction
            statistics reset to zero (all remaining rows)
        if opacity_reset_interval > 0 and (step % opacity_reset_interval == 0
                                           or (white_background and step == densify_from_iter)):
            opacity = logit(min(sigmoid(opacity), reset_opacity)); opacity's Adam moments zeroed
                      (with reset_once only for the rows no reset has gone over yet; then all rows are marked)

Row order is the reference's: [originals that were neither split nor pruned, clones, children (copy-major: first child
of every split Gaussian, then the second ...)], each minus the pruned ones. The reference appends clones, appends
children, removes the split originals, then prunes; we append clones and children in one call and remove split
originals and pruned rows in one call (same result, two state rewrites instead of four).

Deliberate differences from the reference code (each flagged where it is implemented):

* Screen-size pruning is stated relative to the image, and off by default. The reference's
  ``densification_postfix`` zeroes ``max_radii2D`` before its prune test, so its ``max_radii2D > 20`` (pixels) test
  never fires (only the world-size test does), which ``max_screen_fraction = 0`` reproduces. A rule in pixels would
  prune a larger share of the Gaussians the larger the image (20 px is 10 % of a 200-pixel image, 5 % of a 400-pixel
  one); when on, ours is gsplat's: the largest radius over the views since the last densification, divided by each
  view's max(W, H), against ``max_screen_fraction`` (gsplat's ``prune_scale2d``, 0.15); new rows inherit their
  source's value, as in gsplat.
* The large-Gaussian prunes start after ``prune_large_after`` (the reference and gsplat: after the first opacity
  reset, 3000), a setting of its own so that turning resets off (``opacity_reset_interval = 0``, what gsplat 1.5.3
  effectively does: its reset test is always false) keeps them.
* The opacity reset keeps a logit unchanged when its opacity is already below ``reset_opacity`` (the reference round
  trips it through sigmoid and logit: equal up to float rounding, except that very negative logits would become -inf).
* ``reset_once`` (off by default: the reference resets every Gaussian every time) lets each Gaussian go through one
  reset: the first after it was created (the initial points: the first reset). The idea: a row that came back from a
  reset has earned its opacity from the images again, and lowering it again would cost its recovery and prune what
  does not recover in time (gsplat's issue 1011 describes such Gaussians; its PR 1012 proposes resetting only young
  ones). Clones and split children are new rows, not yet reset. Measured no better than the reference's resets or
  none (README, "Each rule changed alone").
* ``weight_prune`` (off by default; not in the reference): at ``densify_until_iter``, the Gaussians whose largest
  blending weight in a training view (a share of the image: :mod:`.weights`) is below it are removed (the trainer
  supplies ``view_weights``), so that the iterations after densification do not carry them.
* ``prune_unseen`` (not in the reference): at ``densify_until_iter``, the Gaussians that no training view shows are
  removed: their blending weight stays below ``raster.alpha_min`` (1/255, the renderer's cut-off for one pixel) of a
  pixel in every training view. Removing them changes no training image by more than that.
* ``error_gate`` (off by default; FastGS's multi-view consistent densification, Ren et al. 2025): a candidate of
  the gradient test is cloned or split only when its error score is at least ``error_gate`` times the model's mean
  score. The score is its blending weight in the high-error pixels of ``error_views`` sampled training views,
  averaged over them (:func:`.weights.error_weights`; the trainer supplies ``view_errors``). FastGS counts the
  high-error pixels of a Gaussian's footprint against a fixed number of pixels; we weigh each by the Gaussian's
  ``T * alpha`` there, so that a Gaussian hidden behind others scores what it shows, and compare with the mean, so
  that the rule does not depend on the image size (a fixed share of the image, tried first, densified a 400-pixel
  image's smaller Gaussians far less than a 200-pixel one's: docs/benchmarks/work_per_step.md).
* ``densify_until_iter`` bounds everything with ``step < densify_until_iter`` exactly as the reference's
  ``if iteration < opt.densify_until_iter`` block (so no opacity reset at step 15000 with the defaults).

Calling order. PyTorch's Adam skips parameters whose ``.grad`` is None, which is what the reference's freshly rebuilt
parameters are after a densification (all six) or an opacity reset (opacity), so its optimizer step is skipped on
those iterations; the ``changed`` flag of the returned info lets the trainer do the same. Every rewritten parameter is
a fresh Dr.Jit leaf with zero gradient (gradients are not carried: see :mod:`.adam`). A trainer that steps anyway
leaves new rows and reset opacities exactly in place (zero gradient, zero moments); kept rows would coast on their
decayed momentum.

Random numbers: the split samples of each densification come from a new PCG32 stream keyed by the strategy's seed and
a counter kept in the state (``draws``), so a resumed run draws the same samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import DensifyConfig, check_section
from ..drjit_utils import concat, fmax, owned_array, quaternion_to_matrix, sigmoid
from .adam import GaussianAdam, gather_rows
from .strategy import StepInfo, Strategy


@dataclass
class DensifyState:
    """Running statistics per Gaussian (Dr.Jit arrays, width N) and the split samples' stream counter.

    Kept in Dr.Jit rather than NumPy: the per-iteration update is three element-wise selects on arrays the renderer
    already holds on the device; in Dr.Jit they are scheduled and fused into the next kernel launch with no host
    synchronization, while NumPy would force a readback of ``radii`` and ``means2d_grad`` every iteration."""

    grad_accum: "mi.Float"      # sum of NDC-space |dL/d mean2d| over the iterations where the Gaussian was visible
    denom: "mi.Float"           # number of those iterations
    max_screen: "mi.Float"      # largest screen radius seen, as a fraction of its view's max(width, height)
    reset_done: "mi.Bool"       # an opacity reset has gone over the row (``reset_once``; kept through row changes)
    draws: int = 0              # densifications that drew split samples (the random stream's counter)

    # What a frozen training step takes of it, and what size classes pad and trim: the per-row arrays. ``draws`` is
    # host state of the refinements, and as a Python int it would key a new recording after every densification that
    # split.
    DRJIT_STRUCT = {"grad_accum": mi.Float, "denom": mi.Float, "max_screen": mi.Float, "reset_done": mi.Bool}

    @property
    def n(self) -> int:
        return dr.width(self.grad_accum)

    def reset(self, n: int) -> None:
        """Zero statistics for ``n`` Gaussians (the counter carries on). Opaque arrays, not literals: a frozen step
        taking the state would otherwise see literal inputs once and evaluated ones after, and record twice."""
        self.grad_accum, self.denom = dr.opaque(mi.Float, 0, n), dr.opaque(mi.Float, 0, n)
        self.max_screen = dr.opaque(mi.Float, 0, n)


def _rows3(t) -> "mi.Vector3f":
    """An (N, 3) tensor's rows as a detached ``Vector3f``."""
    return dr.unravel(mi.Vector3f, dr.detach(t).array)


def _max3(v):
    return fmax(fmax(v.x, v.y), v.z)


def _count(mask) -> int:
    c = dr.count(mask)
    return int(c[0]) if dr.is_array_v(c) else int(c)


def _take_rows(state: DensifyState, rows: "mi.UInt32") -> list:
    """Replace every per-row field of ``state`` by its rows ``rows`` (lazy gathers); returns the new fields."""
    for name, tp in DensifyState.DRJIT_STRUCT.items():
        setattr(state, name, dr.gather(tp, getattr(state, name), rows))
    return [getattr(state, name) for name in DensifyState.DRJIT_STRUCT]


class DefaultStrategy(Strategy):
    """The reference 3DGS densification (see the module docstring). ``extent``: the scene extent
    (``Dataset.scene_extent`` under the run's ``data.extent``); ``seed``: of the split samples; ``white_background``:
    the reference also resets the opacities at ``densify_from_iter`` when it trains on a white background;
    ``empty_background``: the run fits an object on an empty background (``densify.empty_background`` resolved by
    the trainer): that reset on any background, and the screen-size prune at ``empty_screen_fraction`` unless
    ``max_screen_fraction`` sets it."""

    def __init__(self, cfg: DensifyConfig, extent: float, seed: int = 0, white_background: bool = False,
                 empty_background: bool = False):
        check_section("densify", cfg)
        self.cfg = cfg
        self.extent = float(extent)
        self.seed = int(seed)
        self.white_background = bool(white_background)
        self.empty_background = bool(empty_background)
        #: the screen-size prune's threshold (a fraction of the image), 0 when it is off
        self.screen_fraction = float(cfg.max_screen_fraction if cfg.max_screen_fraction > 0 or not empty_background
                                     else cfg.empty_screen_fraction)
        #: ``(gaussians, unit) -> mi.Float``: each Gaussian's largest blending weight over the training views
        #: (:func:`mi_gaussians.optim.weights.max_weights` on them, ``unit`` "share" or "pixels"); the trainer sets it
        #: (``densify.weight_prune``, ``densify.prune_unseen``)
        self.view_weights: Callable | None = None
        #: a weight in pixels below which no view shows a Gaussian (``prune_unseen``): the renderer's cut-off
        #: (``raster.alpha_min``), which the trainer sets with ``view_weights``
        self.unseen_weight: float | None = None
        #: ``(gaussians, step) -> mi.Float``: each Gaussian's error score (``densify.error_gate``); the trainer sets it
        self.view_errors: Callable | None = None

    @classmethod
    def from_config(cls, cfg, extent: float, white_background: bool,
                    empty_background: bool = False) -> "DefaultStrategy":
        return cls(cfg.densify, extent, seed=cfg.seed + 2, white_background=white_background,
                   empty_background=empty_background)

    # ------------------------------------------------------------------ state
    def initialize_state(self, n: int) -> DensifyState:
        state = DensifyState(grad_accum=None, denom=None, max_screen=None, reset_done=dr.opaque(mi.Bool, False, n))
        state.reset(n)
        return state

    row_padding = True      # (its hooks are per row, and an unseen row gathers no statistic)

    def pad_state(self, state: DensifyState, m: int) -> None:
        """``m`` more rows of zero statistics, not yet reset (the rows :func:`.train_step.pad_rows` appends)."""
        for name, tp in DensifyState.DRJIT_STRUCT.items():
            setattr(state, name, concat([getattr(state, name), dr.zeros(tp, m)]))
        dr.eval(*(getattr(state, name) for name in DensifyState.DRJIT_STRUCT))

    def trim_state(self, state: DensifyState, n: int) -> None:
        """The first ``n`` rows of the statistics and reset marks."""
        dr.eval(*_take_rows(state, dr.arange(mi.UInt32, n)))

    def permute_state(self, state: DensifyState, rows) -> None:
        dr.make_opaque(*_take_rows(state, rows))

    def export_state(self, state: DensifyState) -> tuple[dict[str, np.ndarray], dict]:
        arrays = {"grad_accum": np.array(state.grad_accum, dtype=np.float32),
                  "denom": np.array(state.denom, dtype=np.float32),
                  "max_screen": np.array(state.max_screen, dtype=np.float32),
                  "reset_done": np.array(state.reset_done, dtype=np.bool_)}
        return arrays, {"kind": "default", "seed": self.seed, "draws": state.draws}

    def import_state(self, arrays: dict, meta: dict, n: int) -> DensifyState:
        if meta and meta.get("kind", "default") != "default":
            raise ValueError("the checkpoint was written by another densification strategy")
        state = self.initialize_state(n)
        if arrays:
            # (a checkpoint of an earlier version holds max_radii in pixels, of unknown image sizes: that statistic
            # restarts from zero, as after any densification)
            keys = [k for k in ("grad_accum", "denom", "max_screen") if k in arrays]
            lengths = {len(arrays[k]) for k in keys}
            if "grad_accum" not in arrays or "denom" not in arrays or lengths != {n}:
                raise ValueError(f"densification statistics of lengths {sorted(lengths)} for {n} Gaussians")
            state.grad_accum = owned_array(mi.Float, np.asarray(arrays["grad_accum"], np.float32))
            state.denom = owned_array(mi.Float, np.asarray(arrays["denom"], np.float32))
            if "max_screen" in arrays:
                state.max_screen = owned_array(mi.Float, np.asarray(arrays["max_screen"], np.float32))
            if "reset_done" in arrays:      # (an earlier version's checkpoint: no row has been reset yet)
                if len(arrays["reset_done"]) != n:
                    raise ValueError(f"reset marks of length {len(arrays['reset_done'])} for {n} Gaussians")
                state.reset_done = owned_array(mi.Bool, np.asarray(arrays["reset_done"], np.bool_))
            dr.eval(state.grad_accum, state.denom, state.max_screen, state.reset_done)
        if meta:
            self.seed = int(meta.get("seed", self.seed))
            state.draws = int(meta.get("draws", 0))
        return state

    # ------------------------------------------------------------------ hook
    def step_pre_backward(self, params, state, step: int | None, out, collect: bool = True) -> None:
        """With ``absgrad``, ask the backward pass for the per-pixel absolute gradient sums on every iteration
        whose statistics are gathered (``collect``; a frozen step records with and without them)."""
        if self.cfg.absgrad and collect:
            out.request_absgrad()

    def step_post_backward(self, params: GaussianAdam, state: DensifyState, step: int, out) -> StepInfo:
        """Update the statistics and, on the scheduled iterations, densify / prune / reset opacities (:meth:`refine`).

        Counts are read back only on those iterations. When rows or values were rebuilt (``info.changed``) every
        parameter's gradient has been cleared and the trainer should skip the Adam step (see the module docstring)."""
        if step >= self.cfg.densify_until_iter:
            return StepInfo(n=params.n)
        self._check_size(params, state)
        self._accumulate(state, out)
        return self.refine(params, state, step)

    def refine(self, params: GaussianAdam, state: DensifyState, step: int) -> StepInfo:
        """Densify / prune / reset opacities when iteration ``step`` is scheduled to, from the statistics gathered so
        far (nothing otherwise)."""
        info = StepInfo(n=params.n)
        if self._weight_prunes_at(step):
            info.pruned = self._weight_prune(params, state)
            info.changed = True
            params.clear_grads()
            info.n = params.n
            return info
        if step >= self.cfg.densify_until_iter:
            return info
        self._check_size(params, state)
        if self._densifies_at(step):
            info.cloned, info.split, info.pruned = self._densify_and_prune(params, state, step)
            info.densified = info.changed = True
        if self.resets_at(step):
            info.reset = self._reset_opacity(params, state)
            info.opacity_reset = info.changed = True
        if info.changed:
            # The reference rebuilds every parameter on a densification iteration (and opacity on a reset), so they
            # have no gradient and its Adam step skips them. Rows that were not rewritten here still hold this
            # iteration's gradient: clear it, or a trainer that skips the step would add it to the next backward pass.
            params.clear_grads()
            info.n = params.n
        return info

    @staticmethod
    def _check_size(params: GaussianAdam, state: DensifyState) -> None:
        if state.n != params.n:
            raise ValueError(f"densification statistics cover {state.n} Gaussians but the model has {params.n}: "
                             "change rows only through the strategy")

    def _densifies_at(self, step: int) -> bool:
        cfg = self.cfg
        return cfg.densify_from_iter < step < cfg.densify_until_iter and step % cfg.densification_interval == 0

    def resets_at(self, step: int) -> bool:
        """Whether iteration ``step`` resets the opacities."""
        cfg = self.cfg
        every = cfg.opacity_reset_interval
        return every > 0 and step < cfg.densify_until_iter and (
            step % every == 0 or ((self.white_background or self.empty_background) and step == cfg.densify_from_iter))

    def screen_prunes_at(self, step: int) -> bool:
        """Whether the densification of iteration ``step`` applies the screen-size test (``screen_fraction``)."""
        cfg, span = self.cfg, self.cfg.screen_prune_span
        return (self.screen_fraction > 0 and self._densifies_at(step) and step > cfg.prune_large_after
                and (span <= 0 or step <= cfg.prune_large_after + span))

    def _weight_prunes_at(self, step: int) -> bool:
        return (self.cfg.weight_prune > 0 or self.cfg.prune_unseen) and step == self.cfg.densify_until_iter

    def refines_at(self, step: int) -> bool:
        return self._densifies_at(step) or self.resets_at(step) or self._weight_prunes_at(step)

    def updates_state_at(self, step: int) -> bool:
        return step < self.cfg.densify_until_iter

    def update_state(self, state: DensifyState, out, active=True) -> None:
        self._accumulate(state, out, active)

    # ------------------------------------------------------------------ pieces
    def _accumulate(self, st: DensifyState, out, active=True) -> None:
        radii = out.radii
        if dr.width(radii) != st.n:
            raise ValueError(f"render output has {dr.width(radii)} Gaussians, the statistics {st.n}")
        height, width = int(out.rgb.shape[0]), int(out.rgb.shape[1])
        screen = mi.Float(radii) * dr.opaque(mi.Float, 1.0 / max(width, height))
        grad = dr.detach(out.means2d_absgrad if self.cfg.absgrad else out.means2d_grad)
        # the reference rasterizer reports dL/d(mean2d) in NDC units: pixel gradient times W/2 and H/2
        gx = grad.x * dr.opaque(mi.Float, 0.5 * float(width))
        gy = grad.y * dr.opaque(mi.Float, 0.5 * float(height))
        visible = (radii > 0) & active
        st.grad_accum = dr.select(visible, st.grad_accum + dr.sqrt(dr.fma(gx, gx, gy * gy)), st.grad_accum)
        st.denom = dr.select(visible, st.denom + 1.0, st.denom)
        st.max_screen = dr.select(visible, fmax(st.max_screen, screen), st.max_screen)
        # evaluated with the next kernel launch (the optimizer step's dr.eval), without a sync here
        dr.schedule(st.grad_accum, st.denom, st.max_screen)

    def _split_normals(self, st: DensifyState, m: int) -> "mi.Vector3f":
        """m standard-normal 3-vectors from this densification's counted random stream."""
        key = ((self.seed & 0xFFFFFFFF) << 32) | (st.draws & 0xFFFFFFFF)
        st.draws += 1
        rng = mi.PCG32(size=m, initstate=dr.opaque(mi.UInt64, key), initseq=dr.arange(mi.UInt64, m))
        u = [rng.next_float32() for _ in range(4)]
        a = mi.warp.square_to_std_normal(mi.Point2f(u[0], u[1]))
        b = mi.warp.square_to_std_normal(mi.Point2f(u[2], u[3]))
        return mi.Vector3f(a.x, a.y, b.x)

    def _densify_and_prune(self, params: GaussianAdam, st: DensifyState, step: int) -> tuple[int, int, int]:
        """Clone, split and prune; returns the counts (cloned, split originals, pruned)."""
        cfg = self.cfg
        n = st.n
        dense = float(cfg.percent_dense) * self.extent
        sigma_max = _max3(dr.exp(_rows3(params["scales"])))
        grads = dr.select(st.denom > 0, st.grad_accum / st.denom, 0.0)
        high = grads >= float(cfg.absgrad_threshold if cfg.absgrad else cfg.grad_threshold)
        if cfg.error_gate > 0:
            if self.view_errors is None:
                raise ValueError("densify.error_gate needs the training views (DefaultStrategy.view_errors)")
            score = self.view_errors(params.gaussians, step)
            high = high & (score >= float(cfg.error_gate) * dr.mean(score))
        clone_idx = dr.compress(high & (sigma_max <= dense))
        split_mask = high & (sigma_max > dense)
        split_idx = dr.compress(split_mask)
        n_clone, n_split = dr.width(clone_idx), dr.width(split_idx)
        k = int(cfg.split_count)

        # ---- new rows: clones (exact copies), then the children of the split Gaussians, copy-major like torch's
        # .repeat(k, 1) in the reference
        child_src = concat([split_idx] * k)       # (as dr.tile(split_idx, k), whose kernel holds n_split)
        src = concat([clone_idx, child_src])
        max_screen, reset_done = st.max_screen, st.reset_done
        if dr.width(src):
            new_rows = params.rows(src)
            if n_split:
                new_rows.update(self._split_children(params, st, clone_idx, child_src))
            params.append(new_rows)
            max_screen = concat([max_screen, dr.gather(mi.Float, max_screen, src)])
            reset_done = concat([reset_done, dr.zeros(mi.Bool, dr.width(src))])    # new rows: not reset yet

        # ---- prune (over every row, new ones included, as the reference) and remove the split originals
        n_all = n + dr.width(src)
        prune = sigmoid(dr.detach(params["opacities"].array)) < float(cfg.min_opacity)
        if step > cfg.prune_large_after:
            prune = prune | (_max3(dr.exp(_rows3(params["scales"]))) > float(cfg.max_world_scale) * self.extent)
            if self.screen_prunes_at(step):
                # (off by default but on an empty background: dead code in the reference, see the top)
                prune = prune | (max_screen > self.screen_fraction)
        is_split = concat([split_mask, dr.zeros(mi.Bool, n_all - n)])
        remove = prune | is_split
        n_pruned = _count(prune & ~is_split)
        st.reset_done = reset_done
        if n_pruned or n_split:
            self._keep_rows(params, st, ~remove)

        st.reset(params.n)
        return n_clone, n_split, n_pruned

    @staticmethod
    def _keep_rows(params: GaussianAdam, st: DensifyState, keep) -> None:
        """Keep the rows where ``keep`` is true, in the parameters (and their moments) and in the per-row state."""
        params.keep(keep)
        st.reset_done = dr.gather(mi.Bool, st.reset_done, dr.compress(keep))

    def _weight_prune(self, params: GaussianAdam, st: DensifyState) -> int:
        """Remove the Gaussians no training view shows by a ``weight_prune`` share of its image, and with
        ``prune_unseen`` those it shows by less than ``unseen_weight`` of a pixel; returns how many."""
        if self.view_weights is None or (self.cfg.prune_unseen and self.unseen_weight is None):
            raise ValueError("densify.weight_prune and densify.prune_unseen need the training views' weights "
                             "(DefaultStrategy.view_weights, and unseen_weight for prune_unseen)")
        self._check_size(params, st)
        keep = dr.full(mi.Bool, True, params.n)
        if self.cfg.weight_prune > 0:
            keep &= self.view_weights(params.gaussians, "share") >= float(self.cfg.weight_prune)
        if self.cfg.prune_unseen:
            keep &= self.view_weights(params.gaussians, "pixels") >= float(self.unseen_weight)
        removed = params.n - _count(keep)
        if removed:
            self._keep_rows(params, st, keep)
            st.reset(params.n)
        return removed

    def _split_children(self, params: GaussianAdam, st: DensifyState, clone_idx, child_src) -> dict:
        """Means and scales of the new rows [clones, children of ``child_src``]: clones copied, children sampled from
        their source Gaussian with scales divided by ``split_scale_divisor``."""
        m = dr.width(child_src)
        means_c = dr.gather(mi.Vector3f, dr.detach(params["means"].array), child_src)
        scales_c = dr.gather(mi.Vector3f, dr.detach(params["scales"].array), child_src)
        quats_c = dr.gather(mi.Vector4f, dr.detach(params["rotations"].array), child_src)
        sigma_c = dr.exp(scales_c)
        child_means = means_c + quaternion_to_matrix(quats_c) @ (sigma_c * self._split_normals(st, m))
        child_scales = dr.log(sigma_c / float(self.cfg.split_scale_divisor))
        n_clone = dr.width(clone_idx)
        out = {}
        for key, vals in (("means", child_means), ("scales", child_scales)):
            head = gather_rows(params[key].array, clone_idx, 3)
            out[key] = mi.TensorXf(concat([head, dr.ravel(vals)]), (n_clone + m, 3))
        return out

    def _reset_opacity(self, params: GaussianAdam, st: DensifyState) -> int:
        """opacity = min(opacity, reset_opacity) in logit space (with ``reset_once`` only where no reset has gone
        over the row yet), opacity's Adam moments zeroed; returns how many Gaussians were lowered."""
        r = float(self.cfg.reset_opacity)
        o = dr.detach(params["opacities"])
        lower = sigmoid(o.array) >= r
        first = None
        if self.cfg.reset_once:
            first = ~st.reset_done           # the rows this reset goes over; the others keep value and moments
            lower = lower & first
        st.reset_done = dr.opaque(mi.Bool, True, st.n)
        # Logits already below stay bit-identical (the reference's sigmoid/logit round trip differs by rounding only)
        new = dr.select(lower, math.log(r / (1.0 - r)), o.array)
        params.replace("opacities", mi.TensorXf(new, tuple(o.shape)))
        params.reset_moments("opacities", rows=first)
        dr.eval(params["opacities"])
        return _count(lower)
