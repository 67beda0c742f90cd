"""Front-to-back alpha blending of tile-sorted Gaussians, as one ``dr.CustomOp``.

Forward (per pixel, front to back over its tile's instance list, the reference rules exactly)::

    alpha = min(0.99, o * exp(power)),  power = -0.5 (a dx^2 + c dy^2) - b dx dy,  d = mean2d - pixel centre
    skip when alpha < 1/255 (or power > 0); stop before the Gaussian that would bring T below 1e-4
    C += color * alpha * T;  D += depth * alpha * T;  T *= 1 - alpha

It stores only the final transmittance and the index of the last contributor per pixel. Backward walks each
pixel's list back to front from its last contributor, recovering T by division, with no cap on the number of
Gaussians that receive gradients; where the layout says so (:attr:`LaneLayout.skip`: on CUDA) it skips an
instance's arithmetic in a warp none of whose pixels can reach alpha_min (a bound on the exponent per instance,
:func:`_pack_geometry`): on trained models only 7-12 % of the pixel evaluations are hits
(docs/benchmarks/work_per_step.md).

Layout for speed on SIMD CPUs (and coherent on GPUs): one lane handles a column of ``LaneLayout.pixels`` pixels of a
tile (the binning's tile grid: 8 x 8 pixels, 8 per lane, two tiles to a 16-lane SIMD packet, on the LLVM backend;
16 x 16, 4 per lane, on CUDA: ``LANE_LAYOUTS``), so the lanes of a tile are contiguous and read the same instance in
lock-step; the features are packed per instance (8 + 4 floats of the instance's Gaussian, in the order of the
tiles' lists: a tile's walk reads consecutive records, not the Gaussians' scattered ones through the list) and read
with packet gathers; the backward loop of every
group of ``LaneLayout.start_lanes`` lanes (a whole tile: 8 on the CPU, 64 on CUDA) starts at the group's largest
last-contributor index, so a tile's lanes touch the same Gaussian together, and
gradients are accumulated with packet ``scatter_add`` in Dr.Jit's ``Expand`` mode (no atomics
on CPU). The layout changes only the speed: images are identical (for finite inputs), gradients equal up to the order
of float sums.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..config import RasterConfig
from ..drjit_utils import fmin
from .binning import Bins, stable_bucket_perm

TILE = 16
GEO = 8      # packed geometry per Gaussian and per instance: mx, my, log2(e) (-a/2, -b, -c/2) of the conic
             # (a, b, c), opacity, depth, the skip bound; see _pack_geometry
COL = 4      # packed colour per Gaussian and per instance: r, g, b, (pad)


@dataclass(frozen=True)
class LaneLayout:
    """How the blend kernels map pixels to lanes and the image to tiles: tiles of ``tile_cols`` columns by
    ``tile_rows`` rows (powers of two up to 16: the grid the Gaussians are binned into, so that a tile's list holds
    only the Gaussians that reach its pixels), ``pixels`` consecutive pixels of one tile column per lane (a power of
    two dividing ``tile_rows``; more pixels share a lane's gathers and its one gradient scatter per Gaussian, at the
    price of registers; a tile's lanes take its columns first, then its bands of ``pixels`` rows), and the backward
    pass's lanes starting together in groups of ``start_lanes`` (a power of two dividing the lanes of a tile; a SIMD
    packet's worth or more keeps a packet's lanes on the same instance), with ``by_work`` the tiles taken in an
    order that gives the tiles sharing a SIMD packet lists of about equal length (:func:`tile_slots`; for packets
    of more than one tile), and with ``skip`` the backward pass skipping an instance's arithmetic in the lanes none
    of whose pixels its alpha can reach (a branch around a SIMD packet or warp in which no lane can). The layout
    changes the speed, not the result: the footprint that bins a Gaussian does not depend on the tile grid
    (:mod:`.footprint`)."""
    pixels: int
    start_lanes: int
    tile_rows: int = TILE
    tile_cols: int = TILE
    by_work: bool = False
    skip: bool = True

    def __post_init__(self):
        powers = {1, 2, 4, 8, 16, 32, 64, 128, 256}
        if self.tile_rows not in powers or TILE % self.tile_rows:
            raise ValueError(f"LaneLayout: tile_rows = {self.tile_rows}, expected a power of two dividing {TILE}")
        if self.tile_cols not in powers or TILE % self.tile_cols:
            raise ValueError(f"LaneLayout: tile_cols = {self.tile_cols}, expected a power of two dividing {TILE}")
        if self.pixels not in powers or self.tile_rows % self.pixels:
            raise ValueError(f"LaneLayout: pixels = {self.pixels}, expected a power of two dividing the tile's "
                             f"{self.tile_rows} rows")
        if self.start_lanes not in powers or self.lanes_per_tile % self.start_lanes:
            raise ValueError(f"LaneLayout: start_lanes = {self.start_lanes}, expected a power of two dividing the "
                             f"{self.lanes_per_tile} lanes of a tile")

    @property
    def label(self) -> str:
        """What the training loop's statistics call it (``LoopStats.lanes``)."""
        return f"{self.pixels} px/lane, {self.tile_cols}x{self.tile_rows} tiles"

    @property
    def lanes_per_tile(self) -> int:
        return self.tile_cols * self.tile_rows // self.pixels

    @property
    def tile(self) -> tuple[int, int]:
        """A tile's (columns, rows) of pixels: the grid the projection's footprints bin into."""
        return self.tile_cols, self.tile_rows

    def tiles(self, width: int, height: int) -> tuple[int, int]:
        """(tiles_x, tiles_y): the tile grid of a ``width`` x ``height`` image."""
        return (width + self.tile_cols - 1) // self.tile_cols, (height + self.tile_rows - 1) // self.tile_rows

    @property
    def tile_shift(self) -> int:
        return self.lanes_per_tile.bit_length() - 1


# Per backend, measured (benchmarks/layouts.py, docs/benchmarks/speed.md's "Lane layout" and "Tile grid on the CPU"
# tables; a 2-core AVX-512 VM, 16-lane packets; AVX2's 8-lane packets with half the registers are not measured): on
# the CPU a lane blends 8 pixels of a tile column (1.05-1.57x faster than 4 on trained and synthetic models; 16
# pixels spill registers on mi_room). Trained models' Gaussians are a few pixels wide and reach about 2 tiles of
# 16 x 8 pixels, so most of a tile's (pixel, Gaussian) evaluations miss: on tiles of 8 x 8 pixels (8 lanes each, two
# tiles side by side in a 16-lane packet, each half walking its own tile's list) projection, binning and blend
# forward + backward take 0.88-0.92x the time of 16 x 8 tiles on seven trained models (100x100 to 400x400, 42k-138k
# Gaussians), 0.92-0.94x on them rendered at twice their size, 0.98-1.02x at four times, 0.92x on 100k synthetic
# Gaussians at 800x800, 1.09x on 500k and 1.29x on 1M at 1600x1600 (Gaussians about 36 pixels wide: the instances
# grow more than the blend shrinks). 4 x 8 tiles gain more on the trained models and lose 7-12 % at four times their
# size. Its two tiles to a packet are paired by their lists' lengths within bands of tile rows (``by_work``,
# :func:`tile_slots`): render + backward, binning included, 0.84-0.95x on six trained models (100x100 to 400x400), 1.00x
# on 100k synthetic Gaussians at 800x800, 1.01x on 1M at 1600x1600; the frozen training step 0.93x on mi_objects/colmap
# and the 400x400 table. CUDA's default is the layout measured on the H100 (a warp of 32 lanes: 4 pixels, the
# 16 x 16 tile's 64 lanes starting together); training chooses among CUDA_LAYOUTS by the tiles' load (below).
LANE_LAYOUTS = {"llvm": LaneLayout(pixels=8, start_lanes=8, tile_rows=8, tile_cols=8, by_work=True, skip=False),
                "cuda": LaneLayout(pixels=4, start_lanes=64)}


#: The CPU's layout for training while the Gaussians are a few pixels wide (:func:`balanced_layout`): tiles of 4 x 8
#: pixels, four to a packet. Against 8 x 8 tiles, the frozen training step of the 7k models took 0.94x
#: (mi_objects/colmap, 200x200, mean footprint radius 6 pixels), 0.95x (the 400x400 table, 8 pixels) and 0.91x
#: (mi_room/colmap, 6 pixels); render + backward of mi_objects/colmap's model at twice and four times its size (radius 11
#: and 21 pixels) 1.00x and 1.05x, the table's at twice (15 pixels) 1.00x: the smaller tiles' evaluations saved are
#: worth their extra (Gaussian, tile) pairs while a Gaussian reaches only a few of them.
SMALL_TILES = LaneLayout(pixels=8, start_lanes=4, tile_rows=8, tile_cols=4, by_work=True, skip=False)
#: the visible Gaussians' mean footprint radius (the reference's 3-sigma radius, pixels) below which training on the
#: CPU blends with :data:`SMALL_TILES`
SMALL_RADIUS = 10.0


def lane_layout() -> LaneLayout:
    """The active variant's backend's layout."""
    return LANE_LAYOUTS["cuda" if dr.backend_v(mi.Float) == dr.JitBackend.CUDA else "llvm"]


# On CUDA a tile's lanes loop over its instance list, so a kernel lasts at least as long as its heaviest tile takes:
# that tile's list times the pixels each of its lanes evaluates. Trained models of objects on an empty background put
# 8-11 times the mean tile's instances in their heaviest tile, and half the tiles are empty (mi_objects/colmap at
# 200, 400 and 800 pixels square); synthetic scenes of random Gaussians 1.2-1.4 times. Fewer pixels per lane shorten
# that tile's walk, more share each lane's gathers and gradient scatters: measured on an H200
# (docs/benchmarks/gpu.md, 2026-11-29), the blend's forward + backward on the 7k mi_objects/colmap model took
# 11.1 ms with 4 pixels per lane, 7.9 with 2, 6.4 with 1 (4.8 / 4.2 / 3.8 rendered at 800x800), and 100k synthetic
# Gaussians at 800x800 1.8 / 2.2 / 3.1 ms. So training chooses the layout from the load (:func:`balanced_layout`).
#: CUDA's layouts, the most pixels per lane first (a 16 x 16 tile's lanes starting together)
CUDA_LAYOUTS = (LaneLayout(pixels=4, start_lanes=64), LaneLayout(pixels=2, start_lanes=128),
                LaneLayout(pixels=1, start_lanes=256))
#: lanes a GPU keeps running at once, about: an H100's or H200's 132 multiprocessors with 1024 threads each
RESIDENT_LANES = 132 * 1024
#: how many times the mean resident lane's work the heaviest tile's lanes may take
BALANCE = 3.0


def balanced_layout(share: float, cuda: bool, radius: float | None = None) -> LaneLayout:
    """The blend's layout for renders whose heaviest tile holds ``share`` of the instances blended (its pairs over
    all tiles' pairs) and whose visible Gaussians' mean footprint radius is ``radius`` pixels: on CUDA the one with the
    most pixels per lane whose heaviest tile's lanes evaluate at most :data:`BALANCE` times as many (pixel, instance)
    pairs as the mean of the lanes the GPU runs at once; on the CPU, whose few threads take blocks of lanes as they
    come, :data:`SMALL_TILES` below :data:`SMALL_RADIUS`, else the backend's layout. (On the cases measured: 1 pixel per
    lane on trained object models at 200 to 800 pixels square, where that ratio is 7-100 with 4 pixels; 4 on synthetic
    100k Gaussians at 800x800 (0.97), 300k at 1200x1200 and 1M at 1600x1600 (0.40, 0.21); 2 on 30k and 100k at
    400x400 (3.9-4.2 with 4 pixels, 1.9-2.1 with 2).)"""
    if not cuda:
        small = radius is not None and float(radius) < SMALL_RADIUS
        return SMALL_TILES if small else LANE_LAYOUTS["llvm"]
    for layout in CUDA_LAYOUTS:
        if float(share) * layout.pixels * RESIDENT_LANES <= BALANCE * TILE * TILE:
            return layout
    return CUDA_LAYOUTS[-1]


class BlendStats:
    """Filled by the backward pass: what densification needs from the blend.

    A plain class on purpose: ``dr.custom`` rebuilds dataclass arguments (they are PyTrees), which would hide the
    values the backward pass stores here from the caller."""

    def __init__(self):
        self.absgrad_requested = False   # set before dr.backward: also sum |per-pixel dL / d mean2d| (AbsGS)
        self.means2d_grad = None   # dL / d mean2d in pixels, mi.Vector2f (N,), after dr.backward
        self.means2d_absgrad = None   # sum over pixels of |dL_pixel / d mean2d| per axis, when requested
        self.forward_evaluations = None    # (pixel x Gaussian) evaluations of the forward blend (mi.UInt32 (1,))
        self.backward_evaluations = None   # same for the backward blend, after dr.backward



@dataclass
class Frame:
    width: int
    height: int
    width_f: "mi.Float"    # opaque copies so that one kernel serves every resolution's tile grid
    height_f: "mi.Float"
    tiles_x_f: "mi.Float"
    layout: LaneLayout


def _any(masks):
    """OR of a list of masks (without in-place |=, which would modify masks[0])."""
    out = masks[0]
    for m in masks[1:]:
        out = out | m
    return out


def _array_types():
    """(ArrayXf, ArrayXu) of the active variant's backend (packet gathers/scatters need these types)."""
    mod = sys.modules[mi.Float.__module__]
    return mod.ArrayXf, mod.ArrayXu


def _pack(values: list, stride: int) -> "mi.Float":
    """Interleave ``len(values)`` arrays of size N into a flat buffer of N * stride floats (zero padded), as one
    packet scatter of whole records (``stride`` a power of two): every entry is written, so there is no zeroing
    pass, and all in one kernel (one plain scatter per column made a kernel of each: 11 launches a render)."""
    n = dr.width(values[0])
    buf = dr.empty(mi.Float, n * stride)
    rows = [mi.Float(v) for v in values] + [dr.zeros(mi.Float, n)] * (stride - len(values))
    dr.scatter(buf, _array_types()[0](*rows), dr.arange(mi.UInt32, n))
    return buf


LOG2E = 1.4426950408889634


def _per_instance(packed: "mi.Float", stride: int, inst: "mi.UInt32", count=None) -> "mi.Float":
    """The records of ``packed`` (``stride`` floats per Gaussian, :func:`_pack`) of Gaussians ``inst``, one per
    instance in the order of the tiles' lists: the blend's walk of a tile's list then reads consecutive records, not
    the Gaussians' scattered ones through the list (measured on the CPU, trained models at 200x200 and 400x400:
    render + backward 0.7-0.8x; docs/benchmarks/work_per_step.md). One packet gather and one packet scatter per
    instance of the first ``count`` (a device value: the instances in the tiles' ranges, ``Bins.n_blended``; all
    when None); the records past them, the sentinel bucket's and a capacity's tail, are never read and stay
    unwritten (a frozen CPU step on mi_objects/colmap: 0.1-0.2 ms less)."""
    ArrayXf = _array_types()[0]
    m = dr.width(inst)
    buf = dr.empty(mi.Float, m * stride)      # (no zeroing pass: every record read is written)
    i = dr.arange(mi.UInt32, m)
    active = True if count is None else i < count
    dr.scatter(buf, dr.gather(ArrayXf, packed, inst, shape=(stride, m), active=active), i, active=active)
    return buf


SKIP_MARGIN = 1e-3   # log2 units (0.07 %): far above exp2's and log2's float error, so that the bound never skips a hit


def _pack_geometry(mean2d, conic, opacity, depth, alpha_min: float, skip: bool = True) -> "mi.Float":
    """[mx, my, qa, qb, qc, opacity, depth, last] per Gaussian with (qa, qb, qc) = log2(e) (-a/2, -b, -c/2), so that
    the Gaussian falloff is exp(power) = exp2(qa dx^2 + qb dx dy + qc dy^2). ``last``, for a layout that skips
    (:attr:`LaneLayout.skip`): ``lo`` = log2(alpha_min / opacity) less :data:`SKIP_MARGIN` (``+inf`` at opacity 0),
    below which a pixel's exponent cannot reach alpha_min (the exact test still decides every hit); otherwise the
    Gaussian's index, its bits as a float's (:func:`_record_gaussian`): the backward's scatter target comes with the
    record instead of from a gather of the instance list."""
    if skip:
        last = (math.log2(alpha_min) - SKIP_MARGIN) - dr.log2(opacity)
    else:
        last = dr.reinterpret_array(mi.Float, dr.arange(mi.UInt32, dr.width(opacity)))
    return _pack([mean2d.x, mean2d.y, (-0.5 * LOG2E) * conic.x, -LOG2E * conic.y, (-0.5 * LOG2E) * conic.z,
                  opacity, depth, last], GEO)


def _record_gaussian(record_last: "mi.Float") -> "mi.UInt32":
    """The Gaussian of a geometry record of a layout that does not skip (:func:`_pack_geometry`)."""
    return dr.reinterpret_array(mi.UInt32, record_last)


def _pack_instances(mean2d, conic, opacity, depth, color, inst, alpha_min: float, count=None,
                    skip: bool = True) -> tuple:
    """The blend's inputs: the geometry and colour records (:func:`_pack_geometry`, [r, g, b, 0]) per instance of
    the list ``inst`` (:func:`_per_instance`), evaluated. ``skip``: the layout's (what the records' last entry is)."""
    # (packed, then copied, both records in one kernel each: a gather from a buffer with a pending scatter evaluates
    # it, so packing and copying one record after the other made four kernels)
    packed_geo = _pack_geometry(mean2d, conic, opacity, depth, alpha_min, skip)
    packed_col = _pack([color.x, color.y, color.z], COL)
    dr.eval(packed_geo, packed_col)
    geo = _per_instance(packed_geo, GEO, inst, count)
    col = _per_instance(packed_col, COL, inst, count)
    dr.eval(geo, col)
    return geo, col


#: :attr:`LaneLayout.by_work`: the bands of tile rows within which tiles are ordered by their lists' lengths, and the
#: length levels told apart (8 per doubling, lists up to 2^16 instances long)
BAND_ROWS = 2
LENGTH_LEVELS = 128


def _llvm_blocks(lanes: int) -> int:
    """How many blocks Dr.Jit's LLVM backend cuts a kernel of ``lanes`` lanes into, which its threads take as they
    come (drjit-core's ``llvm_ts.cpp``: two per thread up to 2 x 16,384 lanes per thread, then blocks of 16,384)."""
    cores = dr.thread_count()
    if cores <= 1:
        return 1
    if lanes <= 16384 * cores * 2:
        return 2 * cores
    return _ceil_div(lanes, 16384)


def tile_slots(bins: Bins, layout: LaneLayout) -> "mi.UInt32":
    """The tile that each slot of ``layout.lanes_per_tile`` lanes blends, in the forward and the backward pass
    (``bins.n_tiles``: none, a padding slot). The image's tiles in order; with ``layout.by_work``:

    - within each band of :data:`BAND_ROWS` tile rows, the tiles by decreasing length of their lists, so that the
      tiles sharing a SIMD packet (neighbouring slots) walk lists of about equal length: a packet loops until its
      longest tile is done (on trained models the tiles of a packet in image order walked 1.2 times the mean);
    - the bands dealt in turn to the blocks Dr.Jit's LLVM backend cuts a kernel into (:func:`_llvm_blocks`), each
      block a contiguous run of slots, padded to equal length, so that the blocks -- the threads' shares -- hold
      like parts of the image, not one its middle and another its empty top (with more than two blocks per thread,
      which the threads take as they come, the bands stay in order).

    A band keeps together the tiles whose Gaussians share cache lines: sorting the whole image at once (and dealing
    the tiles to the blocks in turn) cost 5-8 % on synthetic scenes, whose tiles are alike. Images are the same bit
    for bit; gradients are summed in another order."""
    n_tiles = bins.n_tiles
    t = dr.arange(mi.UInt32, n_tiles)
    if not layout.by_work:
        return t
    length = dr.gather(mi.UInt32, bins.tile_start, t + 1) - dr.gather(mi.UInt32, bins.tile_start, t)
    level = dr.minimum(mi.UInt32(8.0 * dr.log2(mi.Float(length) + 1.0)), LENGTH_LEVELS - 1)
    band_tiles = bins.tiles_x * BAND_ROWS
    n_bands = _ceil_div(bins.tiles_y, BAND_ROWS)
    key = (t // band_tiles) * LENGTH_LEVELS + ((LENGTH_LEVELS - 1) - level)
    dr.eval(key)
    order = stable_bucket_perm(key, n_bands * LENGTH_LEVELS)    # band by band, each by decreasing length
    blocks, per = _blocks_of_slots(bins.tiles_x, bins.tiles_y, layout)
    if blocks == 1:
        return order
    rank = dr.arange(mi.UInt32, n_tiles)
    band = rank // band_tiles
    slots = dr.full(mi.UInt32, n_tiles, blocks * per)
    dr.scatter(slots, order, (band % blocks) * per + (band // blocks) * band_tiles + (rank - band * band_tiles))
    return slots


def _blocks_of_slots(tiles_x: int, tiles_y: int, layout: LaneLayout) -> tuple[int, int]:
    """(blocks, slots per block) of :func:`tile_slots` with ``layout.by_work``: one block of all tiles when the bands
    stay in order."""
    n_tiles = tiles_x * tiles_y
    blocks = _llvm_blocks(n_tiles * layout.lanes_per_tile)
    if blocks == 1 or blocks > 2 * dr.thread_count():
        return 1, n_tiles
    bands_per_block = _ceil_div(_ceil_div(tiles_y, BAND_ROWS), blocks)
    return blocks, 4 * _ceil_div(bands_per_block * tiles_x * BAND_ROWS, 4)   # whole bands, packets of <= 4 tiles


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


def slot_count(tiles_x: int, tiles_y: int, layout: LaneLayout) -> int:
    """How many slots :func:`tile_slots` makes for a ``tiles_x`` x ``tiles_y`` grid: the blend kernels run over this
    many times ``layout.lanes_per_tile`` lanes."""
    if not layout.by_work:
        return tiles_x * tiles_y
    blocks, per = _blocks_of_slots(tiles_x, tiles_y, layout)
    return blocks * per


def _lane_pixels(frame: Frame, bins: Bins, slots: "mi.UInt32"):
    """The lanes of slots ``slots`` (:func:`tile_slots`): (lane, tile (``bins.n_tiles``: none), whether a tile,
    the start of its list, pixel coordinates (centres) of the lane's column and its pixels' rows, their validity and
    image indices)."""
    layout = frame.layout
    P = layout.pixels
    lane = dr.arange(mi.UInt32, dr.width(slots) * layout.lanes_per_tile)
    tile = dr.gather(mi.UInt32, slots, lane >> layout.tile_shift)
    local = lane & (layout.lanes_per_tile - 1)
    real = tile < bins.n_tiles           # (padding slots: an empty list)
    start = dr.gather(mi.UInt32, bins.tile_start, tile, active=real)
    tile_f = mi.Float(tile)
    ty = dr.floor((tile_f + 0.5) / frame.tiles_x_f)
    tx = tile_f - ty * frame.tiles_x_f
    x = tx * layout.tile_cols + mi.Float(local & (layout.tile_cols - 1))
    y0 = ty * layout.tile_rows + mi.Float(local >> (layout.tile_cols.bit_length() - 1)) * P
    px = x + 0.5
    pys = [y0 + (k + 0.5) for k in range(P)]
    x_ok = x < frame.width_f
    valid = [x_ok & (y0 + k < frame.height_f) for k in range(P)]
    pix = [mi.UInt32(y0 + k) * mi.UInt32(frame.width_f) + mi.UInt32(x) for k in range(P)]
    return lane, tile, real, start, px, pys, valid, pix


def blend_forward(geo: "mi.Float", col: "mi.Float", bins: Bins, frame: Frame, cfg: RasterConfig, slots=None,
                  depth: bool = True):
    """``geo``, ``col``: the features packed per instance (:func:`_pack_instances`). Returns ([r, g, b, depth-sum,
    T] images (H*W each; without ``depth`` the depth sum is None: the loop then carries no depth accumulators and
    writes no depth image), lane-order T (lanes * pixels per lane), lane-order last index (the same), number of
    (pixel x Gaussian) evaluations (lazy UInt32))."""
    P = frame.layout.pixels
    slots = tile_slots(bins, frame.layout) if slots is None else slots
    lane, tile, real, start, px, pys, valid, pix = _lane_pixels(frame, bins, slots)
    n_lanes = dr.width(lane)
    end = dr.gather(mi.UInt32, bins.tile_start, tile + 1, active=real)
    alpha_min, alpha_max, t_min = cfg.alpha_min, cfg.alpha_max, cfg.transmittance_min

    def cond(i, act, T, C, D, last):
        return (i < end) & _any(act)

    def body(i, act, T, C, D, last):
        f = dr.gather(_array_types()[0], geo, i, shape=(GEO, n_lanes))
        mx, my, qa, qb, qc, op, z = f[0], f[1], f[2], f[3], f[4], f[5], f[6]
        dx = mx - px
        ax2 = qa * dx * dx            # shared by the lane's pixels (same column)
        bx = qb * dx
        act, T, C, D, last = list(act), list(T), list(C), list(D), list(last)
        hit, ws, Ts = [], [], []
        for k in range(P):
            dy = my - pys[k]
            power2 = dr.fma(dy, dr.fma(qc, dy, bx), ax2)      # power * log2(e)
            alpha = fmin(op * dr.exp2(power2), alpha_max)
            h = act[k] & (alpha >= alpha_min) & (power2 <= 0)
            test_T = T[k] * (1.0 - alpha)
            stop = h & (test_T < t_min)
            act[k] = act[k] & ~stop
            h = h & ~stop
            hit.append(h)
            # weight alpha T of a hit, 0 otherwise: the updates below become plain multiply-adds
            ws.append(dr.select(h, alpha * T[k], 0.0))
            Ts.append(dr.select(h, test_T, T[k]))
        any_hit = _any(hit)
        c = dr.gather(mi.Vector4f, col, i, active=any_hit)
        rgb = mi.Color3f(c.x, c.y, c.z)
        for k in range(P):
            C[k] = dr.fma(rgb, ws[k], C[k])
            if depth:
                D[k] = dr.fma(z, ws[k], D[k])
            T[k] = Ts[k]
            last[k] = dr.select(hit[k], i + 1, last[k])
        return i + 1, tuple(act), tuple(T), tuple(C), tuple(D), tuple(last)

    state = (mi.UInt32(start),
             tuple(mi.Bool(valid[k]) for k in range(P)),
             tuple(dr.full(mi.Float, 1.0, n_lanes) for _ in range(P)),
             tuple(dr.zeros(mi.Color3f, n_lanes) for _ in range(P)),
             tuple(dr.zeros(mi.Float, n_lanes) for _ in range(P)) if depth else (),
             tuple(mi.UInt32(start) for _ in range(P)))
    i_end, _, T, C, D, last = dr.while_loop(state, cond, body, label="mi_gaussians.blend_forward")

    # r, g, b, depth sum and T in lane order (every lane writes its P pixels as one record: a packet scatter), then
    # read in image order (lazily: the image's consumer gathers each pixel from its lane). Scattering each pixel to
    # the image instead (P scalar scatters a lane and channel, into P rows) took 0.18-0.6 ms a step at 200x200 to
    # 400x400, its own kernel.
    ArrayXf, ArrayXu = _array_types()
    lane_img = []
    for c, v in enumerate(([C[k].x for k in range(P)], [C[k].y for k in range(P)], [C[k].z for k in range(P)],
                           D if depth else None, T)):
        if v is None:
            lane_img.append(None)
            continue
        buf = dr.empty(mi.Float, n_lanes * P)
        dr.scatter(buf, ArrayXf(*v), lane)
        lane_img.append(buf)
    T_lane = lane_img[4]
    last_lane = dr.empty(mi.UInt32, n_lanes * P)
    dr.scatter(last_lane, ArrayXu(*last), lane)
    walked = dr.empty(mi.UInt32, n_lanes)
    dr.scatter(walked, i_end - start, lane)
    # the loop and these writes in one kernel (each consumer of the loop's results in a kernel of its own would run
    # the loop again)
    dr.eval(lane_img, last_lane, walked)
    evaluations = dr.sum(walked) * P        # lazy: read only by benchmarks
    at = _pixel_lanes(frame, bins, slots)
    img = [None if buf is None else dr.gather(mi.Float, buf, at) for buf in lane_img]
    return img, T_lane, last_lane, evaluations


def _pixel_lanes(frame: Frame, bins: Bins, slots: "mi.UInt32") -> "mi.UInt32":
    """Per pixel of the image (row-major), its entry in the lane-order buffers of the blend (lane * P + its row in
    the lane): the inverse of :func:`_lane_pixels`'s mapping, through the tile's slot."""
    layout = frame.layout
    P = layout.pixels
    n_tiles = bins.n_tiles
    slot_of_tile = dr.empty(mi.UInt32, n_tiles)
    dr.scatter(slot_of_tile, dr.arange(mi.UInt32, dr.width(slots)), slots, active=slots < n_tiles,
               mode=dr.ReduceMode.Permute)
    p = dr.arange(mi.UInt32, frame.width * frame.height)
    y = p // frame.width           # (a literal divisor: the width is a kernel constant anyway, as for the tiles)
    x = p - y * frame.width
    col_shift, row_shift = layout.tile_cols.bit_length() - 1, layout.tile_rows.bit_length() - 1
    tile = (y >> row_shift) * bins.tiles_x + (x >> col_shift)
    row = y & (layout.tile_rows - 1)
    local = (x & (layout.tile_cols - 1)) + (row // P) * layout.tile_cols
    lane = dr.gather(mi.UInt32, slot_of_tile, tile) * layout.lanes_per_tile + local
    return lane * P + (row & (P - 1))


def blend_backward(geo, col, bins: Bins, frame: Frame, cfg: RasterConfig, T_lane, last_lane, g_img: list, n: int,
                   absgrad: bool = False, slots=None):
    """Gradients w.r.t. the Gaussians' features, from those packed per instance (``geo``, ``col``): (geo grads
    (N*8), colour grads (N*4), evaluations (lazy UInt32)). ``g_img``: the gradients of the forward's five images;
    that of the depth sum None when the forward had none (its depth gradient is then zero and not computed).

    With ``absgrad`` the padding slots carry AbsGS's statistic: geo slot 7 the sum over pixels of |d L_pixel / d mx|,
    colour slot 3 that of |d L_pixel / d my| (gsplat's ``absgrad``)."""
    layout = frame.layout
    P = layout.pixels
    slots = tile_slots(bins, layout) if slots is None else slots     # (the forward's: the state is per lane)
    lane, tile, real, start, px, pys, valid, pix = _lane_pixels(frame, bins, slots)
    n_lanes = dr.width(lane)
    # every lane of a group starts at the group's largest last-contributor index
    group = layout.start_lanes
    group_last = dr.block_reduce(dr.ReduceOp.Max, last_lane, group * P)
    i0 = dr.gather(mi.UInt32, group_last, lane // group, active=real)
    ArrayXf, ArrayXu = _array_types()
    Tf = dr.gather(ArrayXf, T_lane, lane, shape=(P, n_lanes), active=real)
    last = dr.gather(ArrayXu, last_lane, lane, shape=(P, n_lanes), active=real)
    gpix, gT_times_T = [], []   # dL/d(r, g, b, depth sum), and dL/dT_final * T_final, per pixel
    for k in range(P):
        gpix.append([dr.gather(mi.Float, g_img[c], pix[k], active=valid[k]) if g_img[c] is not None else None
                     for c in range(4)])
        gT_times_T.append(dr.gather(mi.Float, g_img[4], pix[k], active=valid[k]) * Tf[k])
    inst = bins.gaussian
    alpha_min, alpha_max = cfg.alpha_min, cfg.alpha_max
    ggeo = dr.zeros(mi.Float, n * GEO)
    gcol = dr.zeros(mi.Float, n * COL)

    def cond(i, T, acc):
        return i > start

    def body(i, T, acc):
        i = i - 1
        f = dr.gather(ArrayXf, geo, i, shape=(GEO, n_lanes))
        mx, my, qa, qb, qc, op, z, lo = f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7]   # (lo: see below)
        dx = mx - px
        ax2 = qa * dx * dx
        bx = qb * dx
        dys = [my - pys[k] for k in range(P)]
        powers = [dr.fma(dys[k], dr.fma(qc, dys[k], bx), ax2) for k in range(P)]   # bit-identical to the forward
        # pixels this instance can still contribute to (a pixel outside the image never hit: its last is its start)
        live = [i < last[k] for k in range(P)]

        def backward_instance(T, acc, masked: bool):
            ca, cb, cc = (-2.0 / LOG2E) * qa, (-1.0 / LOG2E) * qb, (-2.0 / LOG2E) * qc   # the conic (a, b, c)
            T, acc = list(T), list(acc)
            hit, alphas, unclamped = [], [], []
            for k in range(P):
                power2 = powers[k]
                G = dr.exp2(power2)
                raw = op * G
                alpha = fmin(raw, alpha_max)
                h = live[k] & (alpha >= alpha_min) & (power2 <= 0)
                hit.append(h)
                alphas.append(alpha)
                unclamped.append(raw < alpha_max)
            # Unmasked (``masked`` False), every lane adds, zeros where none of its pixels was hit: on the LLVM
            # backend a mask makes the packet scatter branch on each lane's flag
            active = _any(hit) if masked else True
            # (the records of a layout that does not skip carry their Gaussian where the others carry lo)
            g = dr.gather(mi.UInt32, inst, i, active=active) if layout.skip else _record_gaussian(lo)
            c = dr.gather(mi.Vector4f, col, i, active=active)
            # Per lane, the conic's and the mean's gradients are sums over its pixels of g_pow times 1, dy, dy^2
            # (dx is the lane's): three running sums, the products with dx and the conic once per instance.
            # (separate objects: Dr.Jit's += is in-place)
            s0, s_y, s_yy, g_z, g_r, g_g, g_bl, abs_mx, abs_my = (mi.Float(0.0) for _ in range(9))
            for k in range(P):
                a = alphas[k]
                inv = dr.rcp(1.0 - a)
                Ti = T[k] * inv                         # transmittance in front of this Gaussian
                gc = gpix[k]
                # (without a depth sum: fma(gb, cb, 0) is gb cb, the same gradients bit for bit)
                wgt = dr.fma(gc[0], c.x, dr.fma(gc[1], c.y, gc[2] * c.z if gc[3] is None
                                                 else dr.fma(gc[2], c.z, gc[3] * z)))
                g_alpha = Ti * wgt - acc[k] * inv      # (acc started at the final T's share, dL/dT_final T_final)
                h = hit[k]
                aT_h = dr.select(h, a, 0.0) * Ti         # alpha T of a hit, 0 otherwise: acc adds nothing then
                T[k] = dr.select(h, Ti, T[k])
                acc[k] = dr.fma(wgt, aT_h, acc[k])
                hw = h & unclamped[k]
                g_pow = dr.select(hw, g_alpha * a, 0.0)   # d alpha / d power = o G = alpha when not clamped
                dy = dys[k]
                s0 = s0 + g_pow
                gy = g_pow * dy
                s_y = s_y + gy
                s_yy = dr.fma(gy, dy, s_yy)
                if absgrad:
                    abs_mx = abs_mx + dr.abs(g_pow * (ca * dx + cb * dy))
                    abs_my = abs_my + dr.abs(g_pow * (cc * dy + cb * dx))
                if gc[3] is not None:
                    g_z = dr.fma(gc[3], aT_h, g_z)
                g_r = dr.fma(gc[0], aT_h, g_r)
                g_g = dr.fma(gc[1], aT_h, g_g)
                g_bl = dr.fma(gc[2], aT_h, g_bl)
            # dL/d opacity = sum g_alpha G over the unclamped hits, which is s0 / opacity (their alpha is opacity G):
            # one division per instance instead of a sum per pixel (equal to float rounding)
            g_o = dr.select(op > 0.0, s0 / op, 0.0)
            dx_s0 = dx * s0
            g_mx = -(ca * dx_s0 + cb * s_y)
            g_my = -(cc * s_y + cb * dx_s0)
            g_a = (-0.5 * dx) * dx_s0
            g_b = -(dx * s_y)
            g_c = -0.5 * s_yy
            dr.scatter_add(ggeo, ArrayXf(g_mx, g_my, g_a, g_b, g_c, g_o, g_z, abs_mx), g,
                           active=active, mode=dr.ReduceMode.Expand)
            dr.scatter_add(gcol, mi.Vector4f(g_r, g_g, g_bl, abs_my), g, active=active,
                           mode=dr.ReduceMode.Expand)
            return tuple(T), tuple(acc)

        if not layout.skip:
            # every instance's arithmetic in every lane: on the CPU's 8 x 8 tiles paired by length few SIMD packets
            # have no lane that can be hit, and the skip's masks cost more than it saved
            # (docs/benchmarks/work_per_step.md)
            T, acc = backward_instance(T, acc, masked=False)
            return i, T, acc
        # a SIMD packet or warp where no pixel can reach alpha_min skips the instance's arithmetic
        may_hit = _any([live[k] & (powers[k] >= lo) for k in range(P)])
        T, acc = dr.if_stmt((T, acc), may_hit, lambda T, acc: backward_instance(T, acc, masked=True),
                            lambda *state: state, label="mi_gaussians.blend_backward.hit")
        return i, T, acc

    state = (mi.UInt32(i0), tuple(mi.Float(Tf[k]) for k in range(P)), tuple(gT_times_T))
    dr.while_loop(state, cond, body, label="mi_gaussians.blend_backward")
    evaluations = dr.sum(i0 - start) * P
    return ggeo, gcol, evaluations


class BlendOp(dr.CustomOp):
    """Differentiable blend: inputs are per-Gaussian screen-space features, outputs (r, g, b, depth sum, T) images
    ((r, g, b, T) without ``with_depth``)."""

    def eval(self, mean2d, conic, opacity, color, depth, bins, frame, cfg, stats, with_depth):
        self.bins, self.frame, self.cfg, self.stats = bins, frame, cfg, stats
        self.n = dr.width(opacity)
        self.geo, self.col = _pack_instances(mean2d, conic, opacity, depth, color, bins.gaussian, cfg.alpha_min,
                                             bins.n_blended, frame.layout.skip)
        self.slots = tile_slots(bins, frame.layout)
        img, self.T_lane, self.last_lane, stats.forward_evaluations = blend_forward(self.geo, self.col, bins,
                                                                                    frame, cfg, self.slots, with_depth)
        return tuple(x for x in img if x is not None)

    def forward(self):
        raise NotImplementedError("mi_gaussians: forward-mode derivatives of the blend are not implemented; "
                                  "use reverse mode (dr.backward)")

    def backward(self):
        n = self.n
        absgrad = self.stats.absgrad_requested
        g_img = [mi.Float(x) for x in self.grad_out()]
        if len(g_img) == 4:                      # (no depth sum)
            g_img.insert(3, None)
        if all(g.state == dr.VarState.Literal for g in g_img[:4] if g is not None):
            # No colour or depth gradient (a loss of the alpha alone): the loop's accumulated weights would stay a
            # literal zero, which Dr.Jit's loop recording rejects as a state variable that changes on re-recording.
            g_img[0] = dr.opaque(mi.Float, 0.0, self.frame.width * self.frame.height)
        ggeo, gcol, self.stats.backward_evaluations = blend_backward(
            self.geo, self.col, self.bins, self.frame, self.cfg, self.T_lane, self.last_lane, g_img, n, absgrad,
            self.slots)
        idx = dr.arange(mi.UInt32, n)
        gg = [dr.gather(mi.Float, ggeo, idx * GEO + k) for k in range(7)]
        gc = [dr.gather(mi.Float, gcol, idx * COL + k) for k in range(3)]
        gm = mi.Vector2f(gg[0], gg[1])
        self.stats.means2d_grad = gm
        if absgrad:
            self.stats.means2d_absgrad = mi.Vector2f(dr.gather(mi.Float, ggeo, idx * GEO + 7),
                                                     dr.gather(mi.Float, gcol, idx * COL + 3))
        self.set_grad_in("mean2d", gm)
        self.set_grad_in("conic", mi.Vector3f(gg[2], gg[3], gg[4]))
        self.set_grad_in("opacity", gg[5])
        self.set_grad_in("depth", gg[6])
        self.set_grad_in("color", mi.Color3f(gc[0], gc[1], gc[2]))

    def name(self):
        return "mi_gaussians.Blend"


def make_frame(width: int, height: int, tiles_x: int, layout: LaneLayout | None = None) -> Frame:
    """The blend's frame of a ``width`` x ``height`` image binned into ``tiles_x`` tile columns of ``layout`` (the
    active backend's :func:`lane_layout` when None)."""
    return Frame(width=width, height=height, width_f=dr.opaque(mi.Float, float(width)),
                 height_f=dr.opaque(mi.Float, float(height)), tiles_x_f=dr.opaque(mi.Float, float(tiles_x)),
                 layout=lane_layout() if layout is None else layout)


def blend(mean2d, conic, opacity, color, depth, bins: Bins, frame: Frame, cfg: RasterConfig,
          stats: BlendStats | None = None, with_depth: bool = True):
    """(r, g, b, depth-sum, T) images (H*W each); differentiable when any input has gradients enabled. Without
    ``with_depth`` the depth sum is None, and neither pass computes it (the forward's loop then carries a quarter
    fewer accumulators; r, g, b, T and every gradient are those with it, bit for bit)."""
    stats = BlendStats() if stats is None else stats
    if dr.grad_enabled(mean2d, conic, opacity, color, depth):
        img = list(dr.custom(BlendOp, mean2d, conic, opacity, color, depth, bins, frame, cfg, stats, with_depth))
        if not with_depth:
            img.insert(3, None)
        return tuple(img)
    geo, col = _pack_instances(mean2d, conic, opacity, depth, color, bins.gaussian, cfg.alpha_min,
                               skip=frame.layout.skip)
    img, _, _, stats.forward_evaluations = blend_forward(geo, col, bins, frame, cfg, depth=with_depth)
    return tuple(img)
