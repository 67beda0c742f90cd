"""Learning-rate and SH-degree schedules (optim/schedules.py) against a transcription of the reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mi_gaussians.config import OptimConfig
from mi_gaussians.optim.schedules import expon_lr, sh_degree_at


def reference_expon_lr(step, lr_init, lr_final, lr_delay_steps=0, lr_delay_mult=1.0, max_steps=1000000):
    """utils/general_utils.py get_expon_lr_func(...)(step) of the reference, in NumPy."""
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    if lr_delay_steps > 0:
        delay_rate = lr_delay_mult + (1 - lr_delay_mult) * np.sin(0.5 * np.pi * np.clip(step / lr_delay_steps, 0, 1))
    else:
        delay_rate = 1.0
    t = np.clip(step / max_steps, 0, 1)
    return delay_rate * np.exp(np.log(lr_init) * (1 - t) + np.log(lr_final) * t)


def test_endpoints_and_clamping():
    assert expon_lr(0, 1.6e-4, 1.6e-6, 30_000) == pytest.approx(1.6e-4, rel=1e-12)
    assert expon_lr(30_000, 1.6e-4, 1.6e-6, 30_000) == pytest.approx(1.6e-6, rel=1e-12)
    assert expon_lr(45_000, 1.6e-4, 1.6e-6, 30_000) == pytest.approx(1.6e-6, rel=1e-12)


def test_log_linear_midpoint_is_the_geometric_mean():
    assert expon_lr(15_000, 1.6e-4, 1.6e-6, 30_000) == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6), rel=1e-12)
    assert expon_lr(7_500, 1e-2, 1e-6, 30_000) == pytest.approx(1e-3, rel=1e-12)     # a quarter: 10^(-2 - 1)
    steps = [0, 1, 10, 999, 1000, 12_345, 29_999, 30_000, 31_000]
    got = [expon_lr(s, 2e-3, 3e-5, 30_000) for s in steps]
    assert all(a > b for a, b in zip(got, got[1:-1]))                                # decreasing until max_steps


def test_matches_reference_with_and_without_delay():
    cfg = OptimConfig()
    for s in [0, 1, 7, 100, 2500, 15_000, 29_999, 30_000, 40_000]:
        assert expon_lr(s, cfg.position_lr_init, cfg.position_lr_final, cfg.position_lr_max_steps) == \
            pytest.approx(reference_expon_lr(s, cfg.position_lr_init, cfg.position_lr_final,
                                             max_steps=cfg.position_lr_max_steps), rel=1e-12)
        assert expon_lr(s, 1e-3, 1e-5, 20_000, delay_steps=500, delay_mult=0.01) == pytest.approx(
            reference_expon_lr(s, 1e-3, 1e-5, lr_delay_steps=500, lr_delay_mult=0.01, max_steps=20_000), rel=1e-12)


def test_delay_ramp():
    lr = lambda s: expon_lr(s, 1e-3, 1e-3, 1000, delay_steps=100, delay_mult=0.01)     # constant base rate
    assert lr(0) == pytest.approx(1e-5)                                                # delay_mult * lr
    assert lr(50) == pytest.approx(1e-3 * (0.01 + 0.99 * math.sin(math.pi / 4)))
    assert lr(100) == pytest.approx(1e-3) and lr(500) == pytest.approx(1e-3)
    # no delay_steps: delay_mult is ignored (as in the reference's position schedule)
    assert expon_lr(0, 1e-3, 1e-5, 1000, delay_mult=0.01) == pytest.approx(1e-3)


def test_disabled_and_invalid():
    assert expon_lr(-1, 1e-3, 1e-5, 1000) == 0.0
    assert expon_lr(10, 0.0, 0.0, 1000) == 0.0
    with pytest.raises(ValueError):
        expon_lr(10, 1e-3, 0.0, 1000)
    with pytest.raises(ValueError):
        expon_lr(10, 1e-3, 1e-5, 0)


def test_sh_degree_ramp():
    """Reference: degree 0 at first, +1 at every iteration that is a multiple of 1000 (1-based), capped."""
    cfg = OptimConfig()
    deg = lambda s: sh_degree_at(s, cfg.sh_degree, cfg.sh_increase_interval)
    assert [deg(s) for s in (0, 1, 999, 1000, 1999, 2000, 2999, 3000, 3001, 30_000)] == [0, 0, 0, 1, 1, 2, 2, 3, 3, 3]
    # simulate the reference loop: oneupSHdegree() when iteration % 1000 == 0, before rendering
    active = 0
    for it in range(1, 5001):
        if it % 1000 == 0:
            active = min(active + 1, 3)
        assert deg(it) == active
    assert sh_degree_at(5000, 1, 1000) == 1 and sh_degree_at(5000, 0, 1000) == 0
    assert sh_degree_at(25, 3, 10) == 2
    with pytest.raises(ValueError):
        sh_degree_at(10, 3, 0)
    with pytest.raises(ValueError):
        sh_degree_at(-1, 3, 1000)
