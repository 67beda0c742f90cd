"""The blur *walk* of :mod:`mi_gaussians.image_ops`: a separable 1D Gaussian blur as one kernel whose lanes each move
along one line of an image (down a column, or along a row) over a block of pixels, keeping the last ``window - 1``
samples in the state of a symbolic ``dr.while_loop`` (one load per sample instead of ``window``), and the image
layouts it reads and writes (``_Planes``: natural, or tiled for a vertical walk, see there). What is blurred and what
is made of the blurs (SSIM, its derivative maps) is the caller's: ``tap_fn`` and ``finish_fn``.

Base layer: imports nothing of the package.
"""

from __future__ import annotations

import drjit as dr

_BLOCK_Y = 64     # pixels per lane in a vertical walk   (tuned at 800 x 800 on a 2-core AVX-512 CPU)
_BLOCK_X = 128    # pixels per lane in a horizontal walk
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


def _sweep(srcs: list, shape: tuple, axis: int, weights: list, tap_fn, finish_fn, outs: list, n_sums: int = 0):
    """One blur walk along ``axis`` (0: down the columns, 1: along the rows), zero outside the image.

    ``srcs``: list of ``_Planes``; per sample, ``tap_fn(*values)`` (all the planes' values, in order) gives the
    quantities to blur. Per output pixel, ``finish_fn(blurred, centre sample values, y, p, valid)`` returns (values for
    the planes of ``outs``, in order, and ``n_sums`` terms to sum). Returns the ``n_sums`` totals (Float (1,) each).

    Lanes: axis 0: (block, p) with p = x C + c fastest, padded to whole tiles (a SIMD packet shares a tile column);
    axis 1: (block, y, c) with c fastest."""
    Float = type(srcs[0].data)
    Int, UInt = dr.int32_array_t(Float), dr.uint32_array_t(Float)
    H, W, C = shape
    R = len(weights) // 2
    length = H if axis == 0 else W
    unroll = min(_UNROLL, length)
    if dr.backend_v(Float) == dr.JitBackend.CUDA:
        block = _BLOCK_GPU
    else:
        block = _BLOCK_Y if axis == 0 else _BLOCK_X
    block = -(-length // -(-length // block))     # the blocks share the line evenly: the last is not mostly padding
    block = -(-block // unroll) * unroll
    n_lines = -(-W * C // _TILE) * _TILE if axis == 0 else H * C
    n_blocks = -(-length // block)
    lane = dr.arange(UInt, n_blocks * n_lines)
    line = Int(lane % n_lines)
    p0 = Int(lane // n_lines) * block
    if axis == 0:
        line_ok = line < W * C

        def coords(pos):
            return pos, line
    else:
        line_ok = True
        y_line, c_line = line // C, line % C

        def coords(pos):
            return y_line, pos * C + c_line

    def valid(pos):
        return (pos >= 0) & (pos < length) & line_ok

    def gather(pos):
        ok, (yy, pp) = valid(pos), coords(pos)
        vals = []
        for s in srcs:
            vals.extend(dr.gather(Float, s.data, i, ok) for i in s.indices(shape, yy, pp, UInt))
        return vals

    first = gather(p0 - R)
    ns = len(first)
    window = list(first)
    for k in range(1, 2 * R):
        window.extend(gather(p0 + (k - R)))
    sums0 = [dr.zeros(Float, n_blocks * n_lines) for _ in range(n_sums)]

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


def _identity(*v):
    return v


def _store(blurred, centre, y, p, ok):
    return blurred, ()
