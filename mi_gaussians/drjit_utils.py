"""Generic Dr.Jit helpers that every layer needs: NumPy <-> Dr.Jit copies, float min/max/clamp, a mean that a frozen
function computes as the traced code does (:func:`flat_mean`), the logistic function, quaternion rotation matrices,
the rows of a table of vectors (:func:`row_vectors`) and a concatenation whose kernels do not depend on the parts'
lengths (:func:`concat`).

Float min/max/clamp are written with ``dr.select``: ``dr.minimum/maximum/clip`` on floats abort the process when
Dr.Jit JIT-compiles with libLLVM 15 (see ``drjit-notes.md``). The package selects a newer libLLVM at start-up, but a
user may point ``DRJIT_LIBLLVM_PATH`` at an old one; :func:`fmin`, :func:`fmax` and :func:`fclamp` compile to the
same select instructions on every LLVM and on CUDA, and their gradient follows the selected branch (zero for the
clamped side), like the reference rasterizer's ``min``/``max``.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def owned_tensor(a: np.ndarray) -> "mi.TensorXf":
    """A ``TensorXf`` that owns a float32 copy of ``a``.

    Arrays made from NumPy are zero-copy views: later writes to ``a`` would show through, and foreign alignment makes
    kernels recompile per data set. A scatter into a Dr.Jit allocation gives a real, aligned copy."""
    a = np.ascontiguousarray(a, dtype=np.float32)
    flat = owned_array(mi.Float, a)
    dr.eval(flat)
    return mi.TensorXf(flat, a.shape)


def to_numpy(t) -> np.ndarray:
    """A NumPy copy (float32) of a Dr.Jit tensor or array."""
    return np.array(t, dtype=np.float32, copy=True)


#: Bytes of slack after a NumPy buffer handed to a kernel: Dr.Jit's LLVM scatter of a foreign (zero-copy) source
#: reads whole SIMD packets, past the last element (up to 63 bytes with AVX-512), which crashes when the buffer ends
#: just before an unmapped page (tests/test_drjit_utils.py makes that page unreadable on purpose).
_SLACK = 256


def owned_array(tp, a: np.ndarray):
    """A flat Dr.Jit array of type ``tp`` (``mi.Float``, ``mi.UInt32``, ...) owning a copy of the NumPy array ``a``
    (see :func:`owned_tensor` for why a copy). The kernel reads ``a`` from a padded copy: see :data:`_SLACK`."""
    a = np.ascontiguousarray(a).reshape(-1)
    out = dr.zeros(tp, a.size)
    if a.size:
        padded = np.empty(a.size + _SLACK // a.itemsize, a.dtype)
        padded[:a.size] = a
        dr.scatter(out, tp(padded[:a.size]), dr.arange(mi.UInt32, a.size))
    return out


def concat(arrays: list):
    """The flat arrays ``arrays`` one after the other (empty ones allowed; all of one type), in kernels that do not
    depend on their lengths.

    ``dr.concat`` writes each part at an offset that is a literal in its kernel's code, so every new set of lengths
    builds new kernels: a densification, which appends a different number of rows to every parameter table and
    moment each time, built a dozen kernels anew at each refinement (compiled again on every backend: on CUDA
    a compilation costs milliseconds). Here each part after the first is written at ``arange + offset`` with the
    offset an opaque value: one kernel per part's type and expression, reused at every length."""
    nonempty = [a for a in arrays if dr.width(a)]
    if not nonempty:
        return arrays[0]
    if len(nonempty) == 1:
        return nonempty[0]
    tp = type(nonempty[0])
    Index = dr.uint32_array_t(tp)
    out = dr.empty(tp, sum(dr.width(a) for a in nonempty))
    offset = 0
    for a in nonempty:
        m = dr.width(a)
        idx = dr.arange(Index, m)
        dr.scatter(out, a, idx + dr.opaque(Index, offset) if offset else idx)
        offset += m
    return out


def exact_float_math():
    """A scope in which Dr.Jit traces float arithmetic as written, on the LLVM backend: its ``FastMath`` flag (on by
    default) folds ``a * 0`` into 0 while tracing, which differs from computing it where ``a`` is infinite, NaN or
    negative, and folds only where the 0 is a literal: a frozen recording, whose values are opaque inputs, and the
    traced code then round differently (measured: MCMC training, frozen against traced on one thread, parted at
    iteration 17 with FastMath and stayed equal without; the blend kernels' speed is the same either way). On CUDA
    the flag also selects the approximate division and square root, whose exact versions are software-emulated
    there: left as it is."""
    import contextlib

    if dr.backend_v(mi.Float) == dr.JitBackend.CUDA:
        return contextlib.nullcontext()
    return dr.scoped_set_flag(dr.JitFlag.FastMath, False)


def fmin(a, b):
    """Elementwise minimum of floats, ``dr.select(a < b, a, b)`` (see the module docstring)."""
    return dr.select(a < b, a, b)


def fmax(a, b):
    """Elementwise maximum of floats, ``dr.select(a > b, a, b)`` (see the module docstring)."""
    return dr.select(a > b, a, b)


def fclamp(x, lo, hi):
    """``x`` clamped to ``[lo, hi]`` with :func:`fmax` then :func:`fmin`."""
    return fmin(fmax(x, lo), hi)


def row_vectors(kind, flat, per_row: int = 1, count: int | None = None) -> list:
    """The first ``count`` (default: all) of the ``per_row`` vectors of type ``kind`` (``mi.Vector3f``,
    ``mi.Point3f``, ``mi.Float``, ...) in each row of the flat row-major table ``flat`` (e.g. an (N, K, 3) tensor's
    ``.array``, read as N rows of K ``mi.Vector3f``): a list of ``count`` arrays of N lanes; differentiable.

    The values and gradients of ``dr.gather(kind, flat, arange(N) * per_row + j)``; its reverse mode writes the
    gradient with plain scatters (``ReduceMode.Permute``: every element is read at most once), where the reverse of
    a gather is a scatter-add that costs a loop over a SIMD packet's lanes per component on the LLVM backend (even
    with ``ReduceMode.NoConflicts``): with it the per-Gaussian backward was the step's most expensive kernel after
    the blend. The gathers read ``flat + 0``: the same variable (no copy), but a node of its own in the AD graph,
    whose gradient only these gathers write and which then adds to ``flat``'s like any other."""
    size = dr.size_v(kind) if dr.size_v(kind) > 0 else 1
    count = per_row if count is None else count
    n = dr.width(flat)
    if per_row <= 0 or n % (per_row * size) or not 0 <= count <= per_row:
        raise ValueError(f"row_vectors(): {n} elements are not rows of {per_row} vectors of {size} "
                         f"(reading {count} of them)")
    if count == 0:
        return []
    source = flat + 0.0
    base = dr.arange(dr.uint32_array_t(type(flat)), n // (per_row * size)) * (per_row * size)
    flat_type = type(flat)

    def component(i):           # (one Float each: Dr.Jit's packet scatters of 4 refuse Permute)
        return dr.gather(flat_type, source, base + i, mode=dr.ReduceMode.Permute)

    if size == 1 and dr.depth_v(kind) <= 1:
        return [component(j) for j in range(count)]
    return [kind(*[component(j * size + c) for c in range(size)]) for j in range(count)]


def flat_mean(x):
    """The mean of a flat array: its sum times ``1 / width`` (a Python constant). Dr.Jit 1.5's ``dr.mean`` rounds
    differently inside ``dr.freeze`` than outside it (an ulp, in 40 of 300 arrays of 576 floats on the LLVM
    backend), which made a frozen training step's loss differ from the traced loop's; this gives the same bits in
    both."""
    n = dr.width(x)
    return dr.sum(x) * (1.0 / n) if n else dr.mean(x)


def sigmoid(x):
    """The logistic function 1 / (1 + exp(-x)) of a Dr.Jit array (differentiable)."""
    return dr.rcp(1.0 + dr.exp(-x))


#: The floor of a quaternion's squared norm in its normalization, so that a zero quaternion gives the identity
#: (:func:`quaternion_to_matrix`) and a zero gradient (the projection's hand-written derivative), not NaN.
QUATERNION_FLOOR = 1e-24


def floored_normalization(v, floor: float) -> tuple:
    """(``|v|^2``, ``1 / |v|`` with ``|v|^2`` floored at ``floor``) of vectors: ``v`` normalized is ``v`` times the
    second; :func:`normalization_vjp` is its derivative."""
    n2 = dr.squared_norm(v)
    return n2, dr.rsqrt(fmax(n2, floor))


def normalization_vjp(g, v, n2, r, floor: float):
    """The gradient with respect to ``v`` of ``v * r`` (:func:`floored_normalization`'s ``n2``, ``r`` of ``v``) from
    ``g``, that of the normalized vector; where ``|v|^2`` is at the floor, ``r`` is a constant: ``g r``."""
    return g * r - dr.select(n2 > floor, r * r * r * dr.dot(g, v), 0.0) * v


def quaternion_normalization(q: "mi.Vector4f") -> tuple:
    """:func:`floored_normalization` of quaternions at :data:`QUATERNION_FLOOR`: the normalization of
    :func:`quaternion_to_matrix`, for it and for its derivative."""
    return floored_normalization(q, QUATERNION_FLOOR)


def quaternion_to_matrix(q_wxyz: "mi.Vector4f") -> "mi.Matrix3f":
    """Rotation matrices of (w, x, y, z) quaternions of any norm (normalized here, like the reference's
    ``build_rotation``; a zero quaternion gives the identity). Differentiable."""
    q = q_wxyz * quaternion_normalization(q_wxyz)[1]
    w, x, y, z = q.x, q.y, q.z, q.w
    return mi.Matrix3f(
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )
