"""The blur *walk* of :mod:`mi_gaussians.image_ops`: a separable 1D Gaussian blur as one kernel whose lanes each move
along one line of an image (down a column, or along a row) over a block of pixels, keeping the last ``window - 1``
samples in the state of a symbolic ``dr.while_loop`` (one load per sample instead of ``window``), and the image
layouts it reads and writes (``_Planes``: natural, or tiled for a vertical walk, see there). What is blurred and what
is made of the blurs (SSIM, its derivative maps) is the caller's: ``tap_fn`` and ``finish_fn``. :func:`_sweep_twice`
is a vertical walk that blurs what it makes of its blurs again, in the same kernel.

Base layer: imports nothing of the package.
"""

from __future__ import annotations

import drjit as dr

_BLOCK_Y = 64     # pixels per lane in a vertical walk   (tuned at 800 x 800 on a 2-core AVX-512 CPU)
_BLOCK_X = 128    # pixels per lane in a horizontal walk
_BLOCK_TWICE = 512   # rows per lane in a vertical walk that blurs twice (_sweep_twice), whose lanes start 4 R rows
                     # early: at 200, 400 and 800 pixels square its SSIM loss + gradient took 0.79-0.89x the two
                     # walks' kernel time with 512, 0.90-0.94x with 64 (2-core AVX-512 CPU, 2026-11-30)
_BLOCK_GPU = 16   # both, on CUDA: more, shorter lanes (a GPU needs ~10^5 threads in flight; not tuned)
_UNROLL = 4       # pixels per loop iteration
_TILE_SHIFT = 4
_TILE = 1 << _TILE_SHIFT   # width of a column tile of the tiled layout (16 floats: a 64-byte cache line)


class _Planes:
    """``count`` images of shape (H, W, C) in one flat buffer, in the "natural" layout (row-major (H, W, C), count 1)
    or "tiled": tile t = p // 16 of the column index p = x C + c, then row y, then quantity q, then p % 16::

        index(y, p, q) = ((p // 16) H + y) 16 count + 16 q + p % 16

    so a SIMD packet of 16 lanes walking down one tile column reads ``count`` consecutive cache lines per row."""

    def __init__(self, data, layout: str, count: int = 1):
        self.data, self.layout, self.count = data, layout, count

    @staticmethod
    def empty(Float, shape: tuple, layout: str, count: int = 1) -> "_Planes":
        H, W, C = shape
        n = H * W * C if layout == "natural" else H * (-(-W * C // _TILE) * _TILE) * count
        return _Planes(dr.empty(Float, n), layout, count)

    def indices(self, shape: tuple, y, p, UInt) -> list:
        H, W, C = shape
        if self.layout == "natural":
            return [UInt(y * (W * C) + p)]
        base = UInt(((p >> _TILE_SHIFT) * H + y) * (_TILE * self.count) + (p & (_TILE - 1)))
        return [base + _TILE * q for q in range(self.count)]


def _pair_blur(taps: list, weights: list, m: int):
    """sum_k weights[k] taps[k][m] with symmetric weights (taps k and 2R - k share a multiplication)."""
    R = len(weights) // 2
    v = taps[R][m] * weights[R]
    for k in range(R):
        v = dr.fma(taps[k][m] + taps[2 * R - k][m], weights[k], v)
    return v


def _opaque(Float, v):
    """A 1-entry array kept out of kernel literals (one kernel whatever its value)."""
    a = Float(v)
    dr.make_opaque(a)
    return a


class _Lanes:
    """The lanes of a walk along ``axis`` (0: down the columns, 1: along the rows) over blocks of ``block`` pixels
    (the backend's, unless given), and their reads of ``srcs`` (zero outside the image).

    Lanes: axis 0: (block, p) with p = x C + c fastest, padded to whole tiles (a SIMD packet shares a tile column);
    axis 1: (block, y, c) with c fastest."""

    def __init__(self, srcs: list, shape: tuple, axis: int, block: int | None = None):
        Float = type(srcs[0].data)
        self.Float, self.srcs, self.shape = Float, srcs, shape
        Int, self.UInt = dr.int32_array_t(Float), dr.uint32_array_t(Float)
        H, W, C = shape
        self.length = length = H if axis == 0 else W
        self.unroll = unroll = min(_UNROLL, length)
        if dr.backend_v(Float) == dr.JitBackend.CUDA:
            block = _BLOCK_GPU
        elif block is None:
            block = _BLOCK_Y if axis == 0 else _BLOCK_X
        block = -(-length // -(-length // block))     # the blocks share the line evenly: the last is not mostly padding
        self.block = block = -(-block // unroll) * unroll
        n_lines = -(-W * C // _TILE) * _TILE if axis == 0 else H * C
        self.n = -(-length // block) * n_lines
        lane = dr.arange(self.UInt, self.n)
        line = Int(lane % n_lines)
        self.p0 = Int(lane // n_lines) * block
        if axis == 0:
            self.line_ok = line < W * C
            self.coords = lambda pos: (pos, line)
        else:
            self.line_ok = True
            y_line, c_line = line // C, line % C
            self.coords = lambda pos: (y_line, pos * C + c_line)

    def valid(self, pos):
        return (pos >= 0) & (pos < self.length) & self.line_ok

    def gather(self, pos) -> list:
        """All the sources' values at position ``pos`` of each lane's line."""
        ok, (yy, pp) = self.valid(pos), self.coords(pos)
        vals = []
        for s in self.srcs:
            vals.extend(dr.gather(self.Float, s.data, i, ok) for i in s.indices(self.shape, yy, pp, self.UInt))
        return vals


def _sweep(srcs: list, shape: tuple, axis: int, weights: list, tap_fn, finish_fn, outs: list, n_sums: int = 0):
    """One blur walk along ``axis`` (0: down the columns, 1: along the rows; lanes: :class:`_Lanes`), zero outside
    the image.

    ``srcs``: list of ``_Planes``; per sample, ``tap_fn(*values)`` (all the planes' values, in order) gives the
    quantities to blur. Per output pixel, ``finish_fn(blurred, centre sample values, y, p, valid)`` returns (values for
    the planes of ``outs``, in order, and ``n_sums`` terms to sum). Returns the ``n_sums`` totals (Float (1,) each)."""
    lanes = _Lanes(srcs, shape, axis)
    Float, UInt, unroll, block, p0 = lanes.Float, lanes.UInt, lanes.unroll, lanes.block, lanes.p0
    Int = dr.int32_array_t(Float)
    R = len(weights) // 2
    valid, coords, gather = lanes.valid, lanes.coords, lanes.gather

    first = gather(p0 - R)
    ns = len(first)
    window = list(first)
    for k in range(1, 2 * R):
        window.extend(gather(p0 + (k - R)))
    sums0 = [dr.zeros(Float, lanes.n) for _ in range(n_sums)]

    def body(j, *state):
        win = list(state[:2 * R * ns])
        sums = list(state[2 * R * ns:])
        for u in range(unroll):
            pos = p0 + j + u
            win.extend(gather(pos + R))
            samples = [win[k * ns:(k + 1) * ns] for k in range(2 * R + 1)]
            taps = [tap_fn(*s) for s in samples]
            blurred = [_pair_blur(taps, weights, m) for m in range(len(taps[0]))]
            ok, (yy, pp) = valid(pos), coords(pos)
            values, terms = finish_fn(blurred, samples[R], yy, pp, ok)
            values = iter(values)
            for o in outs:
                for i in o.indices(shape, yy, pp, UInt):
                    dr.scatter(o.data, next(values), i, ok)
            sums = [a + dr.select(ok, t, 0.0) for a, t in zip(sums, terms)]
            win = win[ns:]
        return (j + unroll, *win, *sums)

    state = dr.while_loop((Int(0), *window, *sums0), lambda j, *_: j < block, body, label="ssim_blur")
    sums = list(state[1 + len(window):])
    if sums:
        dr.eval(sums)                            # with the outputs, in the walk's kernel
    return [dr.sum(s) for s in sums]


def _sweep_twice(srcs: list, shape: tuple, weights: list, tap_fn, finish_fn, outs: list, n_sums: int = 0):
    """Two vertical blur walks in one kernel: blur ``tap_fn``'s quantities down the columns, make values of each
    blurred sample with ``finish_fn`` and blur those down the columns too, without storing them between the two.

    Per row, ``finish_fn(blurred, centre sample values, y, p, valid)`` returns (the values to blur again, zero outside
    the image as the second blur's zero padding wants; ``n_sums`` terms to sum over the image's rows). ``outs``: the
    ``_Planes`` receiving the second blur, in order. Returns the ``n_sums`` totals (Float (1,) each). The results are
    those of :func:`_sweep` on ``srcs`` with ``finish_fn`` writing its values to planes, then of :func:`_sweep` on
    those planes with :func:`_store` (the same samples, summed in the same order), without the planes' writes and
    reads in between (the SSIM derivative maps of a training loss)."""
    lanes = _Lanes(srcs, shape, 0, _BLOCK_TWICE)
    Float, UInt, unroll, block, p0 = lanes.Float, lanes.UInt, lanes.unroll, lanes.block, lanes.p0
    Int = dr.int32_array_t(Float)
    R = len(weights) // 2
    valid, gather = lanes.valid, lanes.gather
    line = lanes.coords(0)[1]

    # the first blur's rows r = p0 - R + j for j in [0, steps): the second blur's rows q = r - R, from j = 2R on
    steps = -(-(block + 2 * R) // unroll) * unroll
    first = gather(p0 - 2 * R)
    ns = len(first)
    window = list(first)
    for k in range(1, 2 * R):
        window.extend(gather(p0 - 2 * R + k))
    n_mid = sum(o.count for o in outs)
    mids0 = [dr.zeros(Float, lanes.n) for _ in range(2 * R * n_mid)]
    sums0 = [dr.zeros(Float, lanes.n) for _ in range(n_sums)]

    def body(j, *state):
        win = list(state[:2 * R * ns])
        mids = list(state[2 * R * ns:2 * R * (ns + n_mid)])
        sums = list(state[2 * R * (ns + n_mid):])
        for u in range(unroll):
            r = p0 - R + j + u
            win.extend(gather(r + R))
            samples = [win[k * ns:(k + 1) * ns] for k in range(2 * R + 1)]
            taps = [tap_fn(*smp) for smp in samples]
            blurred = [_pair_blur(taps, weights, m) for m in range(len(taps[0]))]
            ok = valid(r)
            values, terms = finish_fn(blurred, samples[R], r, line, ok)
            mids.extend(dr.select(ok, v, 0.0) for v in values)
            own = ok & (r >= p0) & (r < p0 + block)           # (each row's terms counted by one block)
            sums = [a + dr.select(own, t, 0.0) for a, t in zip(sums, terms)]
            q = r - R
            rows = [mids[k * n_mid:(k + 1) * n_mid] for k in range(2 * R + 1)]
            second = [_pair_blur(rows, weights, m) for m in range(n_mid)]
            write = valid(q) & (q >= p0) & (q < p0 + block)
            second = iter(second)
            for o in outs:
                for i in o.indices(shape, q, line, UInt):
                    dr.scatter(o.data, next(second), i, write)
            win = win[ns:]
            mids = mids[n_mid:]
        return (j + unroll, *win, *mids, *sums)

    state = dr.while_loop((Int(0), *window, *mids0, *sums0), lambda j, *_: j < steps, body,
                          label="ssim_blur_twice")
    sums = list(state[1 + len(window) + len(mids0):])
    if sums:
        dr.eval(sums)                            # with the outputs, in the walk's kernel
    return [dr.sum(s) for s in sums]


def _identity(*v):
    return v


def _store(blurred, centre, y, p, ok):
    return blurred, ()
