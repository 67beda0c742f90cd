"""Tile binning: one instance per (Gaussian, overlapped tile), ordered by (tile, depth), and per-tile ranges.

No gradients flow here. The order is built without a 64-bit key sort:
1. ``argsort`` the N Gaussians by depth once (stable radix sort: equal depths keep index order);
2. expand each Gaussian into its tile instances in that order (exclusive prefix sum of the tile counts, owner lookup
   by a max-scan over the instance starts);
3. one stable bucket pass by tile id (``dr.detail.block_mkperm``), which keeps the depth order inside each tile.

The instance list needs a length. By default it is the exact total, read back to the host (one synchronization).
With ``capacity`` (a frozen training step, which cannot read anything back) the list has that fixed length: instances
past the total go to a sentinel bucket behind the last tile and are never blended, and ``Bins.fits`` (a device
``Bool``) says whether the total fitted. When it did not, instances are missing and the result must not be used: the
caller checks ``fits`` (the frozen trainer masks the step and retries it with a larger capacity).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class Bins:
    """Instance list sorted by (tile, depth) and the per-tile ranges into it."""

    gaussian: "mi.UInt32"     # (M,) Gaussian index of each instance, sorted by (tile, depth)
    tile_start: "mi.UInt32"   # (n_tiles + 1,) instances of tile t are [tile_start[t], tile_start[t + 1])
    n_instances: object       # int; with a capacity, the device total (mi.UInt32, width 1)
    tiles_x: int
    tiles_y: int
    fits: object = True       # with a capacity: mi.Bool (width 1), total <= capacity

    @property
    def n_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


def _next_pow2(n: int) -> int:
    p = 1
    while p < n:
        p *= 2
    return p


def bin_gaussians(depth: "mi.Float", rect: tuple, tile_count: "mi.UInt32", tiles_x: int, tiles_y: int,
                  capacity: int | None = None) -> Bins:
    """Bin Gaussians (detached inputs) into ``tiles_x * tiles_y`` tiles; ``capacity``: see the module docstring."""
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
    order = dr.argsort(depth)
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
    # local // rw in float64: exact for these magnitudes, and free of the scalarized (and SIGFPE-prone) int division
    q = mi.Int32(dr.floor((mi.Float64(local) + 0.5) / mi.Float64(rw)))
    tile = mi.UInt32((ry0 + q) * tiles_x + rx0 + (mi.Int32(local) - q * rw))

    buckets = n_tiles
    if capacity is not None:
        tile = dr.select(valid, tile, n_tiles)       # the sentinel bucket, after every tile
        buckets = n_tiles + 1

    # 3. stable bucket sort by tile id keeps the depth order within each tile
    perm = dr.detail.block_mkperm(tile, size, _next_pow2(buckets))
    gaussian = dr.gather(mi.UInt32, gidx, perm)

    hist = dr.zeros(mi.UInt32, n_tiles + 1)
    dr.scatter_add(hist, mi.UInt32(1), tile + 1, active=valid)
    tile_start = dr.cumsum(hist)                     # inclusive scan of the shifted histogram = [0, starts..., total]
    dr.eval(gaussian, tile_start)
    return Bins(gaussian=gaussian, tile_start=tile_start, n_instances=total, tiles_x=tiles_x, tiles_y=tiles_y,
                fits=fits)
