"""One training iteration as a function of its inputs, recorded once with ``dr.freeze`` and replayed.

Tracing an iteration in Python (the render with its AD graph, the fused L1 + SSIM loss, the backward pass, the
statistics and the Adam update) costs milliseconds of host time, about as much as the kernels of a small model. A
frozen function replays the recorded kernels instead, with no Python in between, and reads nothing back, so the host
can queue the next iteration while the device runs this one. ``dr.freeze`` records again when the structure of the
inputs changes (a new number of Gaussians after densification, another SH degree, a new instance capacity), so a run
holds a handful of recordings.

What freezing requires, and how this module provides it:

- **Every value is an input.** The per-iteration values (target image, camera, background colour, position learning
  rate) arrive as Dr.Jit arrays in :class:`StepInputs`; the model and its Adam state as the
  :class:`~mi_gaussians.optim.adam.GaussianAdam` PyTree; the densification statistics as the strategy's state
  dataclass. Python values that select code (SH degree, whether statistics are updated, the capacity) are arguments,
  so each combination has its own recording.
- **No readback.** Binning takes a fixed ``capacity`` for its instance list instead of reading the count back
  (:func:`~mi_gaussians.raster.binning.bin_gaussians`). Whether the instances fitted, and whether the loss is finite,
  is a device flag ``ok``; the Adam step and the statistics update are masked by it (a masked step is no step: values,
  moments, ``t`` and statistics unchanged), and ``ok`` also gates every later step (``valid`` is chained), so after a
  failed step the model stays exactly as it was before it. The trainer reads the flags every few iterations; on an
  overflow it enlarges the capacity and replays the iterations from the failed one (same views, same backgrounds), on
  a non-finite loss it stops the run naming the iteration. The result is the same model the unfrozen loop trains.

Size classes. A recording is keyed by the widths of its inputs, and Dr.Jit's LLVM backend writes some of them into
the kernels as literals (the per-thread copies of a ``scatter_add`` target in its ``Expand`` mode, e.g. the backward
blend kernel's gradient arrays), so a model of a new size is recorded and compiled again. Densification changes the
size at every refinement (every 100 iterations: ~150 recordings in a 30k run). With ``TrainConfig.row_classes`` > 0
the trainer pads the model to a size class (:func:`row_class`: a geometric ladder, 2^(1/4) apart with 4) with
:func:`inert_rows`, which the projection culls, so that one recording serves every size in a class; it drops them
again (:func:`trim_rows`) before anything on the host reads or changes the rows (refinement, traced iterations,
evaluation, checkpoints). The inert rows change no value the step computes for the others (the instance list, its
order and every sum over it are the same), so the padded run is the unpadded run, bit for bit (tested). A strategy
opts in with ``Strategy.row_padding`` (MCMC does not: its regularizers average over the rows). Off by default: on the
CPU the pads, trims and inert rows cost more than the recordings they save (README, "Performance").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..config import RasterConfig
from ..raster.projection import ViewParams
from ..raster.rasterize import render
from .adam import GaussianAdam
from .losses import alpha_loss, depth_loss, photometric_loss
from .strategy import Strategy

# Instance capacities are taken from this geometric ladder (steps of 2^(1/4), about 19 %), so that the capacity
# changes -- and the step is recorded again -- only when the need moves by a step, while at most about a quarter of
# the instance list is slack.
_CAPACITY_BASE = 4096


def _ladder(value: float, base: int, per_doubling: int) -> int:
    """The smallest rung of the ladder base * 2^(k / per_doubling) (rounded up to a multiple of 256) >= ``value``."""
    k = 0
    while True:
        rung = -(-int(base * 2.0 ** (k / per_doubling)) // 256) * 256
        if rung >= value:
            return rung
        k += 1


def capacity_for(instances: float) -> int:
    """The smallest capacity of the ladder 4096 * 2^(k/8) (rounded up to a multiple of 256) that holds
    ``instances``."""
    return _ladder(instances, _CAPACITY_BASE, 8)


# Size classes of the model (see "Size classes" in the module docstring): rows are padded up to the ladder
# 1024 * 2^(k / TrainConfig.row_classes)
_ROW_CLASS_BASE = 1024

#: The opacity logit of an inert row: sigmoid(-30) ~ 1e-13, far below the 1/255 a Gaussian needs to reach any pixel
INERT_LOGIT = -30.0


def row_class(n: int, per_doubling: int) -> int:
    """The number of rows a model of ``n`` Gaussians is padded to: the smallest rung of the ladder
    1024 * 2^(k / per_doubling) (a multiple of 256) that holds them; ``per_doubling`` 0: ``n`` (no padding)."""
    return int(n) if per_doubling <= 0 else _ladder(n, _ROW_CLASS_BASE, per_doubling)


def inert_rows(params: GaussianAdam, m: int) -> dict:
    """``m`` rows that change nothing a training step computes: opacity logit :data:`INERT_LOGIT` (the projection
    culls them: no tile instance, radius 0, so no gradient, no Adam motion, no densification statistic), the identity
    rotation, zero means, log-scales and colours."""
    out = {}
    for key in params.keys():
        shape = (m,) + tuple(params[key].shape[1:])
        size = m * math.prod(shape[1:])
        if key == "rotations":
            flat = dr.tile(mi.Float([1.0, 0.0, 0.0, 0.0]), m)
        elif key == "opacities":
            flat = dr.full(mi.Float, INERT_LOGIT, size)
        else:
            flat = dr.zeros(mi.Float, size)
        out[key] = mi.TensorXf(flat, shape)
    return out


def pad_rows(params: GaussianAdam, state, strategy: Strategy, rows: int) -> None:
    """Append :func:`inert_rows` to ``params`` (zero moments) and the strategy's neutral statistics to ``state`` up
    to ``rows`` rows (nothing when the model has that many already)."""
    m = int(rows) - params.n
    if m <= 0:
        return
    params.append(inert_rows(params, m))      # (evaluated: every row change leaves opaque leaves)
    strategy.pad_state(state, m)


def trim_rows(params: GaussianAdam, state, strategy: Strategy, n: int) -> None:
    """Drop every row past the first ``n`` of ``params`` (values and moments) and ``state``: the inverse of
    :func:`pad_rows`."""
    if params.n == n:
        return
    params.keep(dr.arange(mi.UInt32, n))
    strategy.trim_state(state, n)


@dataclass
class StepInputs:
    """The per-iteration Dr.Jit values of a training step (a PyTree: a frozen step takes it as an input)."""

    target: "mi.TensorXf"                 # (H, W, 3) image over ``fixed_background``
    transparency: "mi.TensorXf | None"    # (H, W, 1) 1 - alpha, for re-compositing over a random background and
                                          # the alpha loss
    view: ViewParams
    background: tuple                     # (r, g, b) 1-element mi.Float each
    means_lr: "mi.Float"                  # the position learning rate of this iteration (1 element)
    step: "mi.UInt32"                     # the iteration (1 element; keys the strategy's per-iteration noise)
    depth_target: "mi.TensorXf | None" = None   # (H, W) inverse exact depth, 0 where no surface (depth loss)
    depth_weight: "mi.Float | None" = None      # this iteration's depth-loss weight (1 element)
    view_index: "mi.UInt32 | None" = None       # the training view (1 element), whose colour compensation and pose
                                                # correction apply
    exposure_lr: "mi.Float | None" = None       # this iteration's exposure learning rate (1 element)
    pose_lr: "mi.Float | None" = None           # this iteration's pose-correction learning rate (1 element)


def composite_target(target, transparency, background, fixed_background) -> "mi.TensorXf":
    """``target`` (an image over ``fixed_background``) over ``background``: only pixels with ``transparency`` > 0
    change. ``transparency`` None: the image has no alpha and is returned as it is."""
    if transparency is None:
        return target
    # image = straight * a + fixed_bg * (1 - a)  ->  straight * a + bg * (1 - a)
    delta = [b - float(f) for b, f in zip(background, fixed_background)]
    flat = dr.concat(delta) if all(dr.is_array_v(d) for d in delta) else mi.Float(delta)
    return target + transparency * mi.TensorXf(flat, (1, 1, 3))


def training_loss(out, target, lambda_dssim, strategy: Strategy, params: GaussianAdam, depth_target=None,
                  depth_weight=None, exposure=None, view_index=None, ssim_padding: str = "same",
                  transparency=None, alpha_weight: float = 0.0) -> "mi.Float":
    """The loss an iteration minimizes, the one home of its assembly for the frozen step and the traced loop: the
    photometric (L1 + D-SSIM) loss of render ``out`` (through training view ``view_index``'s colour compensation
    when ``exposure`` is given: :func:`.compensation.make_compensation`) against ``target``, the strategy's and the
    compensation's regularizers, and the depth loss weighted by ``depth_weight`` where a ``depth_target`` is
    given; ``ssim_padding``: one of :data:`mi_gaussians.config.SSIM_PADDINGS`; with ``alpha_weight`` > 0 and the
    target's ``transparency`` (1 - its alpha, (H, W, 1)), the L1 distance of the rendered alpha from the target's."""
    image = out.rgb if exposure is None else exposure.apply(out.rgb, view_index)
    loss = photometric_loss(image, target, lambda_dssim, ssim_padding)
    for reg in (strategy.regularization(params), None if exposure is None else exposure.regularization(view_index)):
        if reg is not None:
            loss = loss + reg
    if depth_target is not None:
        loss = loss + depth_weight * depth_loss(out.depth, out.alpha, depth_target)
    if alpha_weight > 0 and transparency is not None:
        loss = loss + float(alpha_weight) * alpha_loss(out.alpha, transparency)
    return loss


class TrainStep:
    """A training iteration without host synchronization: render, loss, backward, statistics, masked Adam step.

    ``step(params, state, inputs, valid, sh_degree, update_state, capacity, exposure, pose, layout)`` returns device
    values ``(loss, ok, instances, blended, max_tile)`` (1 element each: the instance list's length, which the
    capacity must hold, the (Gaussian, tile) pairs blended and the most of them in one tile) and changes ``params``
    and ``state`` in place; ``layout``: the blend's :class:`~mi_gaussians.raster.blend.LaneLayout` (None: the
    backend's), a new one a new recording. ``valid`` is the
    ``ok`` of the previous step (``mi.Bool(True)`` after a synchronization). ``freeze=False`` runs the same code
    traced every time (a reference for tests)."""

    def __init__(self, strategy: Strategy, raster: RasterConfig, lambda_dssim: float, fixed_background,
                 freeze: bool = True, ssim_padding: str = "same", random_background: bool = False,
                 alpha_weight: float = 0.0):
        fixed = tuple(float(b) for b in fixed_background)
        lam = float(lambda_dssim)

        def step(params: GaussianAdam, state, inputs: StepInputs, valid, sh_degree: int, update_state: bool,
                 capacity: int, n: int, exposure, pose, layout):
            # (n, the number of rows (a size class when padded), is an argument so that a new count always makes a
            # new recording)
            view = inputs.view if pose is None else pose.view(inputs.view, inputs.view_index)
            # (the expected depth only for a depth loss: without it the blend carries no depth sum)
            out = render(params.gaussians, view, background=inputs.background, sh_degree=sh_degree,
                         cfg=raster, capacity=capacity, layout=layout, depth=inputs.depth_target is not None)
            strategy.step_pre_backward(params, state, None, out, collect=update_state)
            target = composite_target(inputs.target, inputs.transparency if random_background else None,
                                      inputs.background, fixed)
            loss = training_loss(out, target, lam, strategy, params, inputs.depth_target, inputs.depth_weight,
                                 exposure, inputs.view_index, ssim_padding, inputs.transparency, alpha_weight)
            dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
            ok = valid & out.fits & dr.isfinite(loss)
            if update_state:
                strategy.update_state(state, out, active=ok)
            params.set_learning_rate("means", inputs.means_lr)
            params.step(active=ok)
            strategy.step_post_update(params, state, inputs.step, inputs.means_lr, active=ok)
            if exposure is not None:
                exposure.set_learning_rate(inputs.exposure_lr)
                exposure.step(active=ok)
            if pose is not None:
                pose.set_learning_rate(inputs.pose_lr)
                pose.step(inputs.view_index, active=ok)
            return loss, ok, mi.UInt32(out.n_instances), mi.UInt32(out.n_blended), out.max_tile

        # recordings are made when the model's size changes (densification), so many over a run: no warning
        self._step = dr.freeze(step, limit=4, warn_after=1 << 30) if freeze else step
        self.frozen = freeze

    @property
    def recordings(self) -> int:
        """How many times the step was recorded (0 when not frozen)."""
        return self._step.n_recordings if self.frozen else 0

    def __call__(self, params: GaussianAdam, state, inputs: StepInputs, valid, sh_degree: int, update_state: bool,
                 capacity: int, exposure=None, pose=None, layout=None):
        return self._step(params, state, inputs, valid, int(sh_degree), bool(update_state), int(capacity), params.n,
                          exposure, pose, layout)
