"""Tile binning: one instance per (Gaussian, overlapped tile), ordered by (tile, depth), and per-tile ranges.

No gradients flow here. The order is built without a 64-bit key sort:
1. ``argsort`` the N Gaussians by depth once (stable radix sort: equal depths keep index order);
2. expand each Gaussian into its tile instances in that order (exclusive prefix sum of the tile counts, owner lookup
   by a max-scan over the instance starts);
3. one stable bucket pass by tile id (``dr.detail.block_mkperm``), which keeps the depth order inside each tile.

On CUDA the sorts go through :func:`stable_bucket_perm` and :func:`stable_argsort` (see there): 8-bit digit passes,
so that the tile pass stays stable for any number of tiles, and padded inside a frozen training step, where Dr.Jit
1.5.0 would otherwise crash replaying them.

The instance list needs a length. By default it is the exact total, read back to the host (one synchronization).
With ``capacity`` (a frozen training step, which cannot read anything back) the list has that fixed length: instances
past the total go to a sentinel bucket behind the last tile and are never blended, and ``Bins.fits`` (a device
``Bool``) says whether the total fitted. When it did not, instances are missing and the result must not be used: the
caller checks ``fits`` (the frozen trainer masks the step and retries it with a larger capacity).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import drjit as dr
import mitsuba as mi

if TYPE_CHECKING:       # (footprint needs blend's tile size, and blend these bins)
    from .footprint import Ellipse


@dataclass
class Bins:
    """Instance list sorted by (tile, depth) and the per-tile ranges into it."""

    gaussian: "mi.UInt32"     # (M,) Gaussian index of each instance, sorted by (tile, depth)
    tile_start: "mi.UInt32"   # (n_tiles + 1,) instances of tile t are [tile_start[t], tile_start[t + 1])
    n_instances: object       # int; with a capacity, the device total (mi.UInt32, width 1)
    tiles_x: int
    tiles_y: int
    fits: object = True       # with a capacity: mi.Bool (width 1), total <= capacity
    n_blended: object = None  # instances in the tiles' ranges (a device mi.UInt32, width 1): n_instances less those
                              # of the sentinel bucket (past the capacity, or tiles the footprint's ellipse misses)
    tile_counts: object = None  # (n_tiles + 1,) mi.UInt32: 0, then each tile's instances (tile_start's differences)

    @property
    def n_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


def _next_pow2(n: int) -> int:
    p = 1
    while p < n:
        p *= 2
    return p


#: Buckets per pass on CUDA: Dr.Jit's CUDA ``block_mkperm`` is stable (its "tiny" variant, per-warp histograms in
#: shared memory) only up to a few hundred buckets; above, its shared- and global-memory atomics variants may reorder
#: elements of one bucket, which would reorder the Gaussians of a tile. (Dr.Jit's own argsort uses 8-bit digits on
#: CUDA for the same reason.)
CUDA_RADIX_BUCKETS = 256


def _is_cuda(values) -> bool:
    return dr.backend_v(values) == dr.JitBackend.CUDA


def _needs_padding(values) -> bool:
    """Whether a ``block_mkperm`` of these values is being recorded into a frozen function on CUDA (see
    :func:`_mkperm`)."""
    return _is_cuda(values) and bool(dr.flag(dr.JitFlag.FreezingScope))


def _mkperm(values: "mi.UInt32", bucket_count: int, pad: bool) -> "mi.UInt32":
    """Stable ``block_mkperm`` of the whole array. ``pad``: run it over the array followed by a second block of as
    many zeros and drop the second block's entries. This sidesteps a crash of Dr.Jit 1.5.0's frozen functions on
    CUDA: a replayed ``block_mkperm`` is always handed a (device) bucket-offset buffer, and when the array is a single
    block CUDA's implementation reads that buffer on the host (segmentation fault in ``Recording::replay``); with two
    blocks it does not. The second block is as long as the first because ``block_mkperm`` of a partial last block
    crashes on the LLVM backend (seen above ~16k elements), and is not known to be safe on CUDA.

    The array's width enters the recorded operations as a constant: a frozen function that calls this must be
    recorded again for another width (the training step is keyed by the model's size and the instance capacity)."""
    n = dr.width(values)
    if not pad:
        return dr.detail.block_mkperm(values, n, bucket_count)
    idx = dr.arange(mi.UInt32, 2 * n)
    padded = dr.gather(mi.UInt32, values, idx, active=idx < n)
    perm = dr.detail.block_mkperm(padded, n, bucket_count)
    return dr.gather(mi.UInt32, perm, dr.arange(mi.UInt32, n))


def stable_bucket_perm(values: "mi.UInt32", bucket_count: int, digits: bool | None = None,
                       pad: bool | None = None) -> "mi.UInt32":
    """Stable permutation that groups ``values`` (in ``[0, bucket_count)``) by bucket: gathering ``values`` through
    it gives them in non-decreasing order, equal values in index order.

    LLVM: one ``dr.detail.block_mkperm`` pass (a counting sort, stable for any bucket count). CUDA: passes over
    8-bit digits, least significant first, of :data:`CUDA_RADIX_BUCKETS` buckets each (``digits``), padded inside a
    frozen function (``pad``, see :func:`_mkperm`). Both default to what the backend needs; the tests set them to run
    the CUDA path on the LLVM backend."""
    n = dr.width(values)
    digits = _is_cuda(values) if digits is None else digits
    pad = _needs_padding(values) if pad is None else pad
    if n <= 1:
        return dr.arange(mi.UInt32, n)
    if not digits or bucket_count <= CUDA_RADIX_BUCKETS:
        return _mkperm(values, _next_pow2(bucket_count), pad)       # (block_mkperm wants a power of two)
    bits = (int(bucket_count) - 1).bit_length()
    step = CUDA_RADIX_BUCKETS.bit_length() - 1
    index, keys = dr.arange(mi.UInt32, n), mi.UInt32(values)
    for shift in range(0, bits, step):
        digit = (keys >> shift) & (CUDA_RADIX_BUCKETS - 1)
        dr.eval(digit)
        perm = _mkperm(digit, min(CUDA_RADIX_BUCKETS, 1 << (bits - shift)), pad)
        if shift + step < bits:
            keys = dr.gather(mi.UInt32, keys, perm)
        index = dr.gather(mi.UInt32, index, perm)
        dr.eval(keys, index)
    return index


def stable_argsort(keys: "mi.Float", pad: bool | None = None) -> "mi.UInt32":
    """``dr.argsort(keys)`` (ascending, stable) of Float32 keys. Inside a frozen function on CUDA (``pad``), the same
    radix sort as Dr.Jit's (the floats' order-preserving 32-bit integers, 8-bit digits, least significant first)
    through :func:`stable_bucket_perm`, whose passes replay there; elsewhere ``dr.argsort`` itself."""
    pad = _needs_padding(keys) if pad is None else pad
    if not pad or dr.width(keys) <= 1:
        return dr.argsort(keys)
    if dr.type_v(keys) != dr.VarType.Float32:
        raise TypeError(f"stable_argsort: Float32 keys expected, got {dr.type_v(keys)} (the radix passes are 32-bit)")
    u = dr.reinterpret_array(mi.UInt32, keys)
    ordinal = u ^ ((mi.UInt32(0) - (u >> 31)) | mi.UInt32(0x80000000))   # as Dr.Jit's _to_ordinal_32
    return stable_bucket_perm(ordinal, 1 << 32, digits=True, pad=True)


def bin_gaussians(depth: "mi.Float", rect: tuple, tile_count: "mi.UInt32", tiles_x: int, tiles_y: int,
                  capacity: int | None = None, ellipse: "Ellipse | None" = None, image_size=None) -> Bins:
    """Bin Gaussians (detached inputs) into ``tiles_x * tiles_y`` tiles; ``capacity``: see the module docstring.
    ``ellipse`` (with ``image_size``, the image's (width, height) as ``mi.Float`` values): each instance of a rectangle
    whose tile the Gaussian's ellipse misses goes to the sentinel bucket (:mod:`.footprint`), so it is sorted but
    never blended; ``Bins.n_blended`` counts the others."""
    n_tiles = tiles_x * tiles_y
    depth, tile_count = dr.detach(depth), dr.detach(tile_count)
    n = dr.width(tile_count)
    tx0, ty0, tx1, _ = (dr.detach(r) for r in rect)

    if capacity is None:
        total = int(dr.sum(tile_count)[0]) if n else 0   # the one host readback
        if total == 0:
            return Bins(gaussian=dr.zeros(mi.UInt32, 0), tile_start=dr.zeros(mi.UInt32, n_tiles + 1),
                        n_instances=0, tiles_x=tiles_x, tiles_y=tiles_y)
        size, valid, fits = total, True, True
    else:
        if n == 0 or int(capacity) < 1:
            raise ValueError(f"binning with a capacity needs Gaussians and a capacity >= 1, got {n} and {capacity}")
        size = int(capacity)
        total = dr.sum(tile_count)                       # stays on the device
        fits = total <= size

    # 1. depth order (culled Gaussians have no instances, so their position in the order is irrelevant)
    order = stable_argsort(depth)
    counts = dr.gather(mi.UInt32, tile_count, order)
    offsets = dr.prefix_sum(counts)                  # exclusive

    # 2. expand: instance k belongs to sorted position j = max{j : offsets[j] <= k, counts[j] > 0}
    starts = dr.zeros(mi.UInt32, size)
    # (with a capacity, starts past it are dropped; the exact total needs no test -- and a Python int in the
    # comparison would be a new kernel literal for every count)
    writes = counts > 0 if capacity is None else (counts > 0) & (offsets < size)
    dr.scatter(starts, dr.arange(mi.UInt32, n), offsets, active=writes)
    owner = dr.prefix_reduce(dr.ReduceOp.Max, starts, axis=0, exclusive=False, reverse=False)
    inst = dr.arange(mi.UInt32, size)
    if capacity is not None:
        valid = inst < total
    local = inst - dr.gather(mi.UInt32, offsets, owner)
    gidx = dr.gather(mi.UInt32, order, owner)
    rx0 = dr.gather(mi.Int32, tx0, gidx)
    ry0 = dr.gather(mi.Int32, ty0, gidx)
    rw = dr.gather(mi.Int32, tx1, gidx) - rx0 + 1
    # local // rw without the scalarized (and SIGFPE-prone) integer division: a float32 quotient, off by at most one
    # (its error is below 2^-21 q, q < 2^12 rows of tiles), then corrected exactly in integers
    local_i = mi.Int32(local)
    q = mi.Int32(dr.floor((mi.Float(local) + 0.5) / mi.Float(rw)))
    rest = local_i - q * rw
    q = dr.select(rest < 0, q - 1, dr.select(rest >= rw, q + 1, q))
    tx, ty = rx0 + (local_i - q * rw), ry0 + q
    tile = mi.UInt32(ty * tiles_x + tx)

    buckets = n_tiles
    if ellipse is not None:
        valid = valid & ellipse.touches(gidx, tx, ty, *image_size)
    if capacity is not None or ellipse is not None:
        tile = dr.select(valid, tile, n_tiles)       # the sentinel bucket, after every tile
        buckets = n_tiles + 1

    # (one kernel for both: the sort, the gather through its permutation and the histogram below would each run
    # the expansion and the ellipse test again)
    dr.eval(tile, gidx)

    # 3. stable bucket sort by tile id keeps the depth order within each tile
    perm = stable_bucket_perm(tile, _next_pow2(buckets))
    gaussian = dr.gather(mi.UInt32, gidx, perm)

    # (counted in the sorted order: a SIMD packet's lanes then mostly add into one tile's count, which the LLVM
    # backend's per-packet reduction of equal indices turns into one write)
    sorted_tile = dr.gather(mi.UInt32, tile, perm)
    hist = dr.zeros(mi.UInt32, n_tiles + 1)
    dr.scatter_add(hist, mi.UInt32(1), sorted_tile + 1, active=sorted_tile < n_tiles)   # (the sentinel: not valid)
    tile_start = dr.cumsum(hist)                     # inclusive scan of the shifted histogram = [0, starts..., total]
    dr.eval(gaussian, tile_start)
    return Bins(gaussian=gaussian, tile_start=tile_start, n_instances=total, tiles_x=tiles_x, tiles_y=tiles_y,
                fits=fits, n_blended=dr.gather(mi.UInt32, tile_start, mi.UInt32(n_tiles)), tile_counts=hist)
