"""Small conversions between NumPy and Dr.Jit that every layer needs."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def owned_tensor(a: np.ndarray) -> "mi.TensorXf":
    """A ``TensorXf`` that owns a float32 copy of ``a``.

    Arrays made from NumPy are zero-copy views: later writes to ``a`` would show through, and foreign alignment makes
    kernels recompile per data set. A scatter into a Dr.Jit allocation gives a real, aligned copy."""
    a = np.ascontiguousarray(a, dtype=np.float32)
    n = a.size
    flat = dr.zeros(mi.Float, n)
    if n:
        dr.scatter(flat, mi.Float(a.reshape(-1)), dr.arange(mi.UInt32, n))
    dr.eval(flat)
    return mi.TensorXf(flat, a.shape)


def to_numpy(t) -> np.ndarray:
    """A NumPy copy (float32) of a Dr.Jit tensor or array."""
    return np.array(t, dtype=np.float32, copy=True)
