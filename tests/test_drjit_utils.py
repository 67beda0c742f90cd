"""``owned_array``: NumPy data copied into Dr.Jit memory without reading past the end of the NumPy buffer (Dr.Jit's
scatter of a zero-copy source reads whole SIMD packets; a buffer ending just before an unmapped page crashed
``mi-gs eval`` at random, depending on where the allocator put a model's arrays)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

GUARDED = """
import ctypes, mmap, os, sys
import numpy as np
import mitsuba as mi
mi.set_variant(sys.argv[2])
from mi_gaussians.drjit_utils import owned_array
n = int(sys.argv[1])
page = mmap.PAGESIZE
pages = (4 * n + page - 1) // page
m = mmap.mmap(-1, (pages + 1) * page)
base = ctypes.addressof(ctypes.c_char.from_buffer(m))
assert ctypes.CDLL(None).mprotect(ctypes.c_void_p(base + pages * page), page, 0) == 0   # the page after: unreadable
a = np.frombuffer(m, dtype=np.float32, count=n, offset=pages * page - 4 * n)            # ends at that page
a[:] = np.arange(n, dtype=np.float32)
print(bool(np.array_equal(np.array(owned_array(mi.Float, a)), a)), flush=True)
os._exit(0)
"""


@pytest.mark.parametrize("n", [1, 1000, 16385, 100001, 142326])
def test_owned_array_never_reads_past_the_numpy_buffer(variant, n):
    r = subprocess.run([sys.executable, "-c", GUARDED, str(n), variant], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "True", (r.returncode, r.stdout, r.stderr[-2000:])


def test_owned_array_copies():
    import mitsuba as mi

    from mi_gaussians.drjit_utils import owned_array

    a = np.arange(10, dtype=np.float32)
    out = owned_array(mi.Float, a)
    a[:] = -1                                              # (a copy: later writes do not show through)
    assert np.array_equal(np.array(out), np.arange(10)) and len(owned_array(mi.Float, np.zeros(0))) == 0


def test_exact_float_math_computes_a_times_zero():
    """Dr.Jit's FastMath folds ``a * 0`` into 0 while tracing; the training iterations trace without it (LLVM), so the
    frozen step and the traced loop compute the same thing (tests/test_mcmc.py's frozen = traced failed with it)."""
    import drjit as dr
    import mitsuba as mi

    from mi_gaussians.drjit_utils import exact_float_math

    a = dr.opaque(mi.Float, float("inf"), 3)
    with exact_float_math():
        exact = a * 0.0
    if dr.backend_v(mi.Float) == dr.JitBackend.CUDA:
        pytest.skip("CUDA keeps FastMath (its exact division and square root are software-emulated)")
    assert np.all(np.isnan(np.array(exact)))
    with dr.scoped_set_flag(dr.JitFlag.FastMath, True):
        assert np.all(np.array(a * 0.0) == 0.0)            # (what the flag does: why the scope exists)
    assert dr.flag(dr.JitFlag.FastMath)                     # (the scope restored it)
