"""Screen footprints: the tiles a projected Gaussian is binned into (no gradients).

A Gaussian of opacity ``o`` and dilated 2D covariance ``S = [[a, b], [b, c]]`` reaches alpha >= ``alpha_min``
exactly inside the ellipse ``d^T S^-1 d <= k``, ``k = 2 ln(o / alpha_min)``; the blend skips it everywhere else.

``box`` (``RasterConfig.footprint = "box"``): every tile of the ellipse's axis-aligned bounding box, which
:func:`box` computes for both rules (the rectangle binning expands). ``ellipse`` (the default): only the tiles of
that rectangle whose pixel centres the ellipse's region reaches (:meth:`Ellipse.touches`), the exact
ellipse-rectangle test of AccuTile / Speedy-Splat: a diagonal, elongated Gaussian spans a box of many tiles that it
mostly misses, which the reference's 3-sigma square (and our opacity-aware box) blend for nothing. The rendered
image is bit for bit that of the box rule (only instances whose alpha is below ``alpha_min`` at every pixel of their
tile are left out, and the blend skips those), and so is every gradient where a SIMD packet blends one tile; where it
blends two (the CPU's 8 x 8 tiles) their walks pair up differently when the lists differ, and a Gaussian's
gradient may sum its two tiles' shares in the other order (equal up to float rounding). Only the work changes.

The test, per (Gaussian, tile): the ellipse's region between two rows is convex, so its x-range over the tile's band of
pixel-centre rows ``[y0, y1]`` is ``[min x_l(y), max x_r(y)]`` with ``x_{l,r}(y) = m_x + (b / c) dy -/+ sqrt((k -
dy^2 / c) det / c)`` (``dy = y - m_y``, ``det = ac - b^2``): ``x_r`` is concave with its maximum at the ellipse's
rightmost point ``dy_r = b sqrt(k / a)``, ``x_l`` convex with its minimum at ``-dy_r``, so both extremes are those
points clamped into the band. The tile is touched when that range meets its pixel-centre columns ``[x0, x1]``. The
test is evaluated once per instance (in the binning kernel) and stored, so the counts and the instance list cannot
disagree. Margins (relative, and absolute in pixels) make it conservative against float rounding in this test and in
the blend's own evaluation of the exponent: a tile near the boundary is kept, never dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..drjit_utils import fclamp, fmax, fmin
from .blend import TILE

#: Relative and absolute (pixels) slack added to a footprint against float rounding; it only adds work.
REL_MARGIN = 1e-3
ABS_MARGIN = 1e-2
#: Per unit of the covariance's condition a c / det: float32 rounding of ``det`` (and of the blend's exponent) grows
#: with it (a thin ellipse), so the relative margin does too (about 16 float32 epsilons per unit).
CONDITION_MARGIN = 1e-6


@dataclass
class Ellipse:
    """Per-Gaussian (width N, detached) parameters of the alpha >= alpha_min ellipse, as the per-tile test needs them."""

    mx: "mi.Float"
    my: "mi.Float"
    slope: "mi.Float"         # b / c: the ellipse's x centre moves by slope * dy along y
    half2: "mi.Float"         # det / c: the squared half-width at dy is (k - dy^2 / c) * half2
    inv_c: "mi.Float"
    k: "mi.Float"             # the threshold k, enlarged by the relative margin
    ext_y: "mi.Float"         # sqrt(k c): the y half-extent
    dy_r: "mi.Float"          # dy of the rightmost point, b sqrt(k / a)
    tile: tuple = (TILE, TILE)   # the tile grid's (columns, rows) per tile

    def touches(self, g: "mi.UInt32", tx: "mi.Int32", ty: "mi.Int32", width_f: "mi.Float",
                height_f: "mi.Float") -> "mi.Bool":
        """Whether Gaussian ``g``'s ellipse reaches the pixel centres of tile (``tx``, ``ty``) (see the module
        docstring; conservative)."""
        def get(v):
            return dr.gather(mi.Float, v, g)

        mx, my, slope, half2, inv_c = get(self.mx), get(self.my), get(self.slope), get(self.half2), get(self.inv_c)
        k, ext_y, dy_r = get(self.k), get(self.ext_y), get(self.dy_r)
        ts, rows = float(self.tile[0]), float(self.tile[1])
        y0 = mi.Float(ty) * rows + 0.5
        y1 = fmin(mi.Float(ty) * rows + (rows - 1.0), height_f - 1.0) + 0.5
        x0 = mi.Float(tx) * ts + 0.5
        x1 = fmin(mi.Float(tx) * ts + (ts - 1.0), width_f - 1.0) + 0.5
        lo = fmax(y0 - my - ABS_MARGIN, -ext_y)
        hi = fmin(y1 - my + ABS_MARGIN, ext_y)
        yr = fclamp(dy_r, lo, hi)
        yl = fclamp(-dy_r, lo, hi)
        xr = mx + slope * yr + dr.sqrt(fmax(k - yr * yr * inv_c, 0.0) * half2) + ABS_MARGIN
        xl = mx + slope * yl - dr.sqrt(fmax(k - yl * yl * inv_c, 0.0) * half2) - ABS_MARGIN
        return (lo <= hi) & (xl <= x1) & (xr >= x0)


def box(m: "mi.Point2f", a: "mi.Float", b: "mi.Float", c: "mi.Float", det: "mi.Float", k: "mi.Float",
        valid: "mi.Bool", width_f: "mi.Float", height_f: "mi.Float", ellipse: bool, tile: tuple = (TILE, TILE)):
    """The tile rectangle (tx0, ty0, tx1, ty1) (inclusive, ``mi.Int32``; tiles of ``tile`` = (columns, rows)
    pixels) of the ellipse ``d^T S^-1 d <= k`` (detached inputs), its tile count (0 where not ``valid`` or off screen)
    and, with ``ellipse``, the :class:`Ellipse` whose test drops the rectangle's tiles it misses (``None``
    otherwise)."""
    ex = dr.sqrt(fmax(k * a, 0.0)) * (1 + REL_MARGIN) + ABS_MARGIN
    ey = dr.sqrt(fmax(k * c, 0.0)) * (1 + REL_MARGIN) + ABS_MARGIN
    valid = valid & dr.isfinite(ex) & dr.isfinite(ey) & dr.isfinite(m.x) & dr.isfinite(m.y)
    # pixels i whose centre i + 0.5 lies within [m - e, m + e]
    i0 = dr.ceil(m.x - ex - 0.5)
    i1 = dr.floor(m.x + ex - 0.5)
    j0 = dr.ceil(m.y - ey - 0.5)
    j1 = dr.floor(m.y + ey - 0.5)
    valid &= (i1 >= 0) & (i0 <= width_f - 1) & (j1 >= 0) & (j0 <= height_f - 1) & (i0 <= i1) & (j0 <= j1)
    ts, rows = float(tile[0]), float(tile[1])
    tx0 = mi.Int32(dr.floor(fmax(i0, 0.0) / ts))
    tx1 = mi.Int32(dr.floor(fmin(i1, width_f - 1) / ts))
    ty0 = mi.Int32(dr.floor(fmax(j0, 0.0) / rows))
    ty1 = mi.Int32(dr.floor(fmin(j1, height_f - 1) / rows))
    count = dr.select(valid, mi.UInt32((tx1 - tx0 + 1) * (ty1 - ty0 + 1)), 0)
    shape = None
    if ellipse:
        # safe where not valid (those have no instances): nothing below is read for them
        a_, c_ = fmax(a, 1e-30), fmax(c, 1e-30)
        ke = fmax(k, 0.0) * (1 + REL_MARGIN + CONDITION_MARGIN * a_ * c_ / fmax(det, 1e-30)) ** 2
        inv_c = dr.rcp(c_)
        shape = Ellipse(mx=m.x, my=m.y, slope=b * inv_c, half2=fmax(det, 0.0) * inv_c, inv_c=inv_c, k=ke,
                        ext_y=dr.sqrt(ke * c_), dy_r=b * dr.sqrt(ke / a_), tile=tile)
    return (tx0, ty0, tx1, ty1), count, valid, shape
