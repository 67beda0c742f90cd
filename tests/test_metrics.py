"""Evaluation metrics (metrics.py): PSNR known values, SSIM agreeing with the loss, LPIPS availability."""

from __future__ import annotations

import importlib.util
import math
import subprocess
import tempfile
import sys

import numpy as np
import pytest

from mi_gaussians import metrics
from mi_gaussians.drjit_utils import owned_tensor
from mi_gaussians import image_ops


def test_psnr_known_values():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.2, 0.8, (16, 12, 3))
    assert metrics.psnr(ref + 0.1, ref) == pytest.approx(20.0, abs=1e-9)      # MSE 0.01
    assert metrics.psnr(ref - 0.01, ref) == pytest.approx(40.0, abs=1e-7)     # MSE 1e-4
    assert metrics.psnr(ref, ref) == math.inf
    assert metrics.psnr(np.zeros((4, 4, 3)), np.ones((4, 4, 3))) == pytest.approx(0.0)
    half = ref.copy()
    half[:8] += 0.1                                                            # MSE 0.005 over all pixels/channels
    assert metrics.psnr(half, ref) == pytest.approx(10 * math.log10(1 / 0.005))


def test_psnr_clamps_to_unit_range():
    ref = np.full((8, 8, 3), 0.95)
    img = ref + 0.2                                  # clamped to 1: error 0.05 -> 26.02 dB
    assert metrics.psnr(img, ref) == pytest.approx(20 * math.log10(1 / 0.05))
    assert metrics.psnr(img, ref, clamp=False) == pytest.approx(20 * math.log10(1 / 0.2))
    with pytest.raises(ValueError):
        metrics.psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))


def test_ssim_agrees_with_the_loss_and_the_numpy_port():
    rng = np.random.default_rng(1)
    a = rng.random((30, 41, 3))
    b = np.clip(a + 0.15 * rng.standard_normal(a.shape), 0, 1)
    s = metrics.ssim_np(a, b)
    assert s == pytest.approx(float(image_ops.ssim(owned_tensor(a), owned_tensor(b))[0]), abs=1e-7)
    assert s == pytest.approx(metrics.ssim_float64(a, b), abs=1e-5)
    assert metrics.ssim_np(a, a) == pytest.approx(1.0, abs=1e-6)
    # clamping: out-of-range renders are scored as clamp(render, 0, 1)
    assert metrics.ssim_np(a * 1.5, b) == pytest.approx(metrics.ssim_np(np.clip(a * 1.5, 0, 1), b), abs=1e-7)


@pytest.mark.skipif(importlib.util.find_spec("torch") is not None, reason="torch is installed here")
def test_lpips_unavailable_without_torch():
    ok, reason = metrics.lpips_available()
    assert ok is False and "torch" in reason and "\n" not in reason
    with pytest.raises(RuntimeError, match="torch"):
        metrics.lpips_vgg(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)))


def test_metrics_imports_no_training_code():
    """Scoring, SSIM's Dr.Jit kernels included, loads nothing of ``mi_gaussians.optim`` (the static check of every
    import, those inside functions included, is tests/test_layering.py)."""
    code = ("import sys, numpy as np, mitsuba as mi; mi.set_variant('llvm_ad_rgb'); import mi_gaussians.metrics as m; "
            "a = np.random.default_rng(0).random((16, 16, 3)); m.psnr(a, 0.5 * a); m.ssim_np(a, 0.5 * a); "
            "m.ssim_float64(a, 0.5 * a); bad = [k for k in sys.modules if k.startswith('mi_gaussians.optim')]; "
            "assert not bad, bad")
    # (outside the source tree, so that the installed package is the one imported)
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120, cwd=tempfile.gettempdir())
