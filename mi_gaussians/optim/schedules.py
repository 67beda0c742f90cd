"""Pure step -> value schedules of 3DGS training (no state, no Dr.Jit).

Steps are the reference's iteration numbers: 1-based, the first optimization step is ``step = 1`` (the reference loops
``for iteration in range(1, iterations + 1)`` and calls ``update_learning_rate(iteration)`` and, when
``iteration % 1000 == 0``, ``oneupSHdegree()`` before rendering that iteration).
"""

from __future__ import annotations

import math


def expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int, delay_steps: int = 0,
             delay_mult: float = 1.0) -> float:
    """Learning rate at ``step``: the reference's ``get_expon_lr_func(lr_init, lr_final, lr_delay_steps=delay_steps,
    lr_delay_mult=delay_mult, max_steps=max_steps)(step)``.

    Log-linear interpolation ``exp((1 - t) log(lr_init) + t log(lr_final))`` with ``t = clip(step / max_steps, 0, 1)``
    (so the midpoint is the geometric mean and steps past ``max_steps`` keep ``lr_final``), times the delay factor
    ``delay_mult + (1 - delay_mult) sin(pi/2 clip(step / delay_steps, 0, 1))`` when ``delay_steps > 0`` (a ramp from
    ``delay_mult * lr`` at step 0 to the full rate at ``delay_steps``), else 1. Returns 0 for ``step < 0`` or when
    ``lr_init == lr_final == 0`` (the reference's way of disabling a parameter).

    Note that the reference never passes ``lr_delay_steps`` for the position learning rate, so its
    ``position_lr_delay_mult`` (0.01) has no effect there; pass ``delay_steps`` explicitly to use the ramp."""
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    if not (lr_init > 0.0 and lr_final > 0.0):
        raise ValueError(f"log-linear learning-rate interpolation needs positive rates (or both 0 to disable), got "
                         f"lr_init={lr_init!r}, lr_final={lr_final!r}")
    if max_steps <= 0:
        raise ValueError(f"max_steps must be positive, got {max_steps!r}")
    if delay_steps > 0:
        ramp = min(max(step / delay_steps, 0.0), 1.0)
        delay_rate = delay_mult + (1.0 - delay_mult) * math.sin(0.5 * math.pi * ramp)
    else:
        delay_rate = 1.0
    t = min(max(step / max_steps, 0.0), 1.0)
    return delay_rate * math.exp(math.log(lr_init) * (1.0 - t) + math.log(lr_final) * t)


def position_lr(step: int, o, extent: float) -> float:
    """The position learning rate at ``step`` of a run with the settings ``o`` (an ``OptimConfig``): the reference's
    schedule, scaled by the scene extent."""
    return extent * expon_lr(step, o.position_lr_init, o.position_lr_final, o.position_lr_max_steps,
                             delay_steps=o.position_lr_delay_steps, delay_mult=o.position_lr_delay_mult)


def depth_weight(step: int, o) -> float:
    """The depth-loss weight at ``step`` of a run with the settings ``o``: decaying over the run's schedule
    (``position_lr_max_steps``, which a resume with more iterations keeps, as it keeps every schedule)."""
    return expon_lr(step, o.depth_weight, o.depth_weight_final, o.position_lr_max_steps)


def warmup_expon_lr(step: int, lr: float, warmup_steps: int, start_factor: float, final_factor: float,
                    max_steps: int) -> float:
    """gsplat's bilateral-grid schedule at the 1-based iteration ``step``: ``ChainedScheduler([LinearLR(
    start_factor, total_iters=warmup_steps), ExponentialLR(gamma=final_factor ** (1 / max_steps))])`` stepped once
    after each optimizer step, so the k-th step (``k = step - 1`` before it) uses ``lr (start_factor + (1 -
    start_factor) min(k, warmup_steps) / warmup_steps) gamma^k``."""
    if max_steps <= 0 or warmup_steps <= 0:
        raise ValueError(f"max_steps and warmup_steps must be positive, got {max_steps!r}, {warmup_steps!r}")
    k = max(int(step) - 1, 0)
    warm = start_factor + (1.0 - start_factor) * min(k, warmup_steps) / warmup_steps
    return lr * warm * final_factor ** (k / max_steps)


def sh_degree_at(step: int, max_degree: int, interval: int) -> int:
    """Active SH degree at the 1-based iteration ``step``: ``min(max_degree, step // interval)``.

    The reference starts at degree 0 and raises it by one at the start of every iteration that is a multiple of
    ``interval`` (1000), before rendering: iterations 1..999 use degree 0, 1000..1999 degree 1, 2000..2999 degree 2,
    3000 and later degree 3 (for ``max_degree = 3``). ``step = 0`` (before training) gives 0."""
    if interval <= 0:
        raise ValueError(f"the SH degree interval must be a positive number of iterations, got {interval!r}")
    if max_degree < 0:
        raise ValueError(f"max_degree must be >= 0, got {max_degree!r}")
    if step < 0:
        raise ValueError(f"step must be >= 0 (1-based iterations), got {step!r}")
    return min(int(max_degree), int(step) // int(interval))
