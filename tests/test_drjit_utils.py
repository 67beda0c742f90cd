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


@pytest.mark.parametrize("kind_name, size, per_row, count", [("Float", 1, 2, 2), ("Vector3f", 3, 15, 8),
                                                             ("Vector4f", 4, 1, 1), ("Point3f", 3, 1, 1)])
def test_row_vectors_equal_gathers_in_values_and_both_derivatives(kind_name, size, per_row, count):
    """``row_vectors`` (plain scatters in reverse mode) gives the values and gradients of ``dr.gather`` (a
    scatter-add), also when the table's gradient has another contribution besides the gathers (which a plain
    scatter into the table's own gradient would overwrite), and leaves the elements it does not read at 0."""
    import drjit as dr
    import mitsuba as mi

    from mi_gaussians.drjit_utils import row_vectors

    kind = getattr(mi, kind_name)
    rows = 37
    values = np.random.default_rng(3).normal(size=rows * per_row * size).astype(np.float32)

    def run(read):
        flat = mi.Float(values)
        dr.enable_grad(flat)
        vectors = read(flat)
        loss = dr.sum(flat * flat) * 0.5                   # (another contribution to the table's gradient)
        for j, v in enumerate(vectors):
            for c in range(size):
                comp = v if size == 1 else v[c]
                loss += dr.sum(dr.sin(comp) * (j + 1) + comp * comp * (c + 2))
        dr.backward(loss)
        tangent = mi.Float(np.linspace(-1, 1, len(values)).astype(np.float32))
        flat2 = mi.Float(values)
        dr.enable_grad(flat2)
        dr.set_grad(flat2, tangent)
        outs = read(flat2)
        dr.forward_to(*outs)
        fwd = [np.array(dr.grad(o)) for o in outs]
        return [np.array(v) for v in vectors], np.array(dr.grad(flat)), fwd

    def gathered(flat):
        base = dr.arange(mi.UInt32, rows) * per_row
        return [dr.gather(kind, flat, base + j) for j in range(count)]

    ours, theirs = run(lambda flat: row_vectors(kind, flat, per_row, count)), run(gathered)
    for a, b in zip(ours[0] + [ours[1]] + ours[2], theirs[0] + [theirs[1]] + theirs[2]):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)
    unread = ours[1].reshape(rows, per_row, size)[:, count:]
    np.testing.assert_allclose(unread, values.reshape(rows, per_row, size)[:, count:], rtol=1e-6)  # (the extra
    with pytest.raises(ValueError, match="7 elements are not rows of 4 vectors of 3"):        # term's only)
        row_vectors(mi.Vector3f, mi.Float([1.0] * 7), 4)


def test_flat_mean_has_the_same_bits_in_a_frozen_function(ordered_sums):
    """Dr.Jit 1.5's ``dr.mean`` rounds differently inside ``dr.freeze`` than outside for some inputs (here: found
    among 300 random arrays, else the premise is gone and ``flat_mean`` could go); ``flat_mean`` never does, and is
    the mean."""
    import drjit as dr
    import mitsuba as mi

    from mi_gaussians.drjit_utils import flat_mean

    rng = np.random.default_rng(0)
    frozen_mean, frozen_flat = dr.freeze(lambda x: dr.mean(x * 1.0)), dr.freeze(lambda x: flat_mean(x * 1.0))
    mean_differs = 0
    for _ in range(300):
        a = mi.Float(rng.random(576).astype(np.float32) * rng.random() * 3)
        mean_differs += float(frozen_mean(a)[0]) != float(dr.mean(a * 1.0)[0])
        assert float(frozen_flat(a)[0]) == float(flat_mean(a * 1.0)[0])
        exact = float(np.mean(np.array(a), dtype=np.float64))
        assert abs(float(flat_mean(a)[0]) - exact) <= 1e-6 * float(dr.max(a)[0])
    assert mean_differs > 0


@pytest.mark.parametrize("kind", ["Float", "UInt32", "Bool"])
def test_concat_equals_numpy_concatenation_with_empty_parts(kind):
    import drjit as dr
    import mitsuba as mi

    from mi_gaussians.drjit_utils import concat

    tp = getattr(mi, kind)
    rng = np.random.default_rng(3)
    parts_np = [rng.integers(0, 2 if kind == "Bool" else 1000, size=m).astype(
        {"Float": np.float32, "UInt32": np.uint32, "Bool": bool}[kind]) for m in (5, 0, 17, 1, 0, 40)]
    parts = [tp(p) if p.size else dr.zeros(tp, 0) for p in parts_np]
    np.testing.assert_array_equal(np.array(concat(parts)), np.concatenate(parts_np))
    assert np.array(concat([dr.zeros(tp, 0), parts[2]])).tolist() == parts_np[2].tolist()
    assert dr.width(concat([dr.zeros(tp, 0)])) == 0


def test_concat_kernels_do_not_depend_on_the_lengths():
    """``dr.concat`` writes each part at a literal offset (a new kernel per set of lengths); ``concat`` does not."""
    import drjit as dr
    import mitsuba as mi
    from kernel_log import KernelLog

    from mi_gaussians.drjit_utils import concat

    def run(a: int, b: int, log) -> list:
        x, y = dr.arange(mi.Float, a) * 2.0, dr.arange(mi.Float, b) + 1.0
        out = concat([x, y])
        dr.eval(out)
        assert np.array(out).tolist() == [2.0 * i for i in range(a)] + [i + 1.0 for i in range(b)]
        return sorted(h for _, h in log.cut())

    with KernelLog() as log:
        run(3, 4, log)
        assert run(10, 7, log) == run(1000, 33, log)
