"""The order of the model's rows (Gaussians) while it trains: by where the Gaussians are (``optim.row_order``).

Densification appends its clones and split children after the other rows and pruning closes the gaps, so after a
few refinements the Gaussians that one tile blends lie all over the parameter tables. Every per-instance read of the
step (the copy of the blend's records, the footprints' test in the binning) and every per-instance write (the
backward blend's gradient sums) then reaches a different part of memory. Sorted by a Morton code of their means,
the Gaussians near one another in space, and so in a view, are near one another in memory too.

Measured on the CPU (2 cores, ``llvm_ad_rgb``; frozen steps resumed from the same checkpoint with its rows sorted or
not, three turns): mi_objects/colmap's 7k model 0.92x, the 400x400 table's 0.96x (docs/benchmarks/
work_per_step.md). A render is the same for any order of the rows (the depth sort is stable, and equal depths keep
the order of the rows they came from: a clone stays after its original); what changes is which row a densification's
random draws fall to.

:func:`order_rows` sorts the rows of the parameter owner and of the strategy's state together (the strategy's
:meth:`~.strategy.Strategy.permute_state`); the trainer calls it when a run starts and after each refinement that
changed rows.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..drjit_utils import fclamp

#: Bits of the Morton code per axis (30 in all: one ``UInt32`` sort key).
BITS = 10
#: The code's box, per axis: these percentiles of the means (of a sample of at most SAMPLE rows). The Gaussians
#: outside share the border cells: floaters far away do not squeeze the others into a handful of cells.
PERCENTILES = (1.0, 99.0)
SAMPLE = 4096


def _spread_bits(v: "mi.UInt32") -> "mi.UInt32":
    """The low 10 bits of ``v`` moved to every third bit (bit i to bit 3 i)."""
    v = v & 0x3FF
    v = (v | (v << 16)) & 0x30000FF
    v = (v | (v << 8)) & 0x300F00F
    v = (v | (v << 4)) & 0x30C30C3
    return (v | (v << 2)) & 0x9249249


def _box(means: "mi.Float", n: int) -> np.ndarray:
    """(3, 2): per axis, the low and high :data:`PERCENTILES` of the finite means of every ``n / SAMPLE``-th row (one
    small readback)."""
    step = max(1, n // SAMPLE)
    # (the step and the box below as opaque values: as literals, each refinement's would compile its kernels anew)
    rows = dr.arange(mi.UInt32, -(-n // step)) * dr.opaque(mi.UInt32, 3 * step)
    sample = np.array(dr.gather(mi.Float, means, dr.repeat(rows, 3) + dr.tile(dr.arange(mi.UInt32, 3),
                                                                             dr.width(rows))))
    sample = sample.reshape(-1, 3).astype(np.float64)
    box = np.zeros((3, 2))
    for axis in range(3):
        x = sample[:, axis][np.isfinite(sample[:, axis])]
        if x.size:
            box[axis] = np.percentile(x, PERCENTILES)
    return box


def morton_codes(means: "mi.Float") -> "mi.UInt32":
    """Per row of the flat (N * 3) table ``means``, the Morton code of its cell in a 2^10 grid per axis over the box
    of :func:`_box` (a mean outside it in the border cell; a non-finite one in cell 0)."""
    n = dr.width(means) // 3
    if n == 0:
        return dr.zeros(mi.UInt32, 0)
    box = _box(means, n)
    idx = dr.arange(mi.UInt32, n) * 3
    code = dr.zeros(mi.UInt32, n)
    cells = float(1 << BITS)
    for axis in range(3):
        lo, hi = (float(v) for v in box[axis])
        scale = dr.opaque(mi.Float, cells / (hi - lo) if hi > lo else 0.0)
        lo = dr.opaque(mi.Float, lo)
        x = dr.gather(mi.Float, means, idx + axis)
        cell = mi.UInt32(fclamp((x - lo) * scale, 0.0, cells - 1.0))
        code = code | (_spread_bits(dr.select(dr.isfinite(x), cell, 0)) << axis)
    return code


def spatial_order(means: "mi.Float") -> "mi.UInt32":
    """The rows of the flat (N * 3) table ``means`` by their Morton code (:func:`morton_codes`); rows of one code
    keep their order (a stable sort)."""
    n = dr.width(means) // 3
    if n <= 1:
        return dr.arange(mi.UInt32, n)
    return dr.argsort(morton_codes(means))


def order_rows(params, strategy, state) -> "mi.UInt32":
    """Sort the rows of ``params`` (a :class:`~.adam.GaussianAdam`: values and moments) and of the strategy's
    ``state`` by :func:`spatial_order` of the means; returns the permutation (new row -> old row)."""
    perm = spatial_order(dr.detach(params["means"].array))
    dr.eval(perm)
    params.keep(perm)
    strategy.permute_state(state, perm)
    return perm
