"""``render(gaussians, camera)``: projection -> binning -> blending, differentiable w.r.t. every raw parameter.

    out = render(g, cam, background=(r, g, b), sh_degree=None)
    out.rgb    TensorXf (H, W, 3)   C + T * background
    out.alpha  TensorXf (H, W)      1 - T
    out.depth  TensorXf (H, W)      expected depth sum(z_i w_i) / sum(w_i) (0 where nothing was hit); None when
                                    rendered with ``depth=False`` (neither pass then computes it)
    out.radii  Int32 (N,)           reference screen radius (ceil(3 sqrt(lambda_max)) px), 0 when culled
    out.means2d_grad                dL / d(projected mean) in pixels, (N,) Vector2f, available after dr.backward
    out.means2d_absgrad             sum over pixels of |dL_pixel / d(projected mean)| (AbsGS), after dr.backward,
                                    when ``out.request_absgrad()`` was called before it

Gradients reach the raw parameters of ``g`` through Dr.Jit's AD (``dr.enable_grad(g.means)``, ...,
``dr.backward(loss)``); the blend's own backward pass is the hand-written one of ``blend.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from ..config import RasterConfig
from ..data.camera import Camera
from ..drjit_utils import fmax
from ..model.gaussians import Gaussians
from .binning import Bins, bin_gaussians
from . import blend as _blend_module
from .blend import BlendStats, LaneLayout, blend, make_frame
from .projection import GaussianArrays, ViewParams, project
from .projection_backward import project_model


@dataclass
class RenderOutput:
    rgb: "mi.TensorXf"
    alpha: "mi.TensorXf"
    depth: "mi.TensorXf | None"
    radii: "mi.Int32"
    n_instances: object       # (Gaussian, tile) pairs of the footprints' rectangles, the instance list's length:
                              # int; with a capacity, a device mi.UInt32 (width 1)
    fits: object = True       # with a capacity: mi.Bool (width 1), the instances fitted (else do not use the image)
    n_blended: object = 0     # the pairs blended (a device mi.UInt32, width 1; raster.footprint 'ellipse' leaves out
                              # the rectangles' tiles a Gaussian does not reach)
    _stats: BlendStats = field(repr=False, default=None)
    _tile_counts: object = field(repr=False, default=None)    # Bins.tile_counts

    @property
    def max_tile(self) -> "mi.UInt32":
        """The most pairs blended in one tile (a device mi.UInt32, width 1, reduced when read: what
        :func:`~.blend.balanced_layout` weighs against ``n_blended``)."""
        return dr.max(self._tile_counts) if self._tile_counts is not None else dr.zeros(mi.UInt32, 1)

    @property
    def means2d_grad(self) -> "mi.Vector2f":
        """Gradient of the loss w.r.t. the projected 2D means (pixels), filled by ``dr.backward``."""
        if self._stats.means2d_grad is None:
            return dr.zeros(mi.Vector2f, dr.width(self.radii))
        return self._stats.means2d_grad

    def request_absgrad(self) -> None:
        """Ask the coming backward pass for :attr:`means2d_absgrad` as well (call before ``dr.backward``)."""
        self._stats.absgrad_requested = True

    @property
    def means2d_absgrad(self) -> "mi.Vector2f":
        """AbsGS's statistic (gsplat's ``absgrad``): per Gaussian and axis, the sum over pixels of the absolute value of
        each pixel's contribution to dL/d(projected mean); filled by ``dr.backward`` after :meth:`request_absgrad`."""
        if not self._stats.absgrad_requested:
            raise ValueError("means2d_absgrad: call request_absgrad() before dr.backward")
        if self._stats.means2d_absgrad is None:
            return dr.zeros(mi.Vector2f, dr.width(self.radii))
        return self._stats.means2d_absgrad


def _background(background) -> tuple:
    """Three opaque ``mi.Float`` values: a random background per iteration must not make every kernel a new one.
    Dr.Jit values (e.g. the inputs of a frozen training step) are used as they are."""
    bg = tuple(background)
    if len(bg) != 3:
        raise ValueError(f"background must have 3 components (r, g, b), got {background!r}")
    return tuple(b if dr.is_array_v(b) else dr.opaque(mi.Float, float(b)) for b in bg)


def render(g: Gaussians, camera: Camera | ViewParams, background=(0.0, 0.0, 0.0), sh_degree: int | None = None,
           cfg: RasterConfig = RasterConfig(), capacity: int | None = None,
           layout: LaneLayout | None = None, depth: bool = True) -> RenderOutput:
    """Render raw 3DGS parameters (see the module docstring). ``capacity``: a fixed length of the tile-instance list,
    for a frozen training step that cannot read the count back (see :mod:`.binning`; check ``out.fits``).
    ``layout``: the blend's lanes (:class:`~.blend.LaneLayout`; the backend's default when None): the speed only.
    ``depth``: whether to render ``out.depth`` (without it the blend carries no depth sum, which a training step
    without a depth loss does not read: 0.95-0.97x its time on the CPU; the other outputs and every gradient of
    them are the same bit for bit)."""
    deg = g.sh_degree if sh_degree is None else int(sh_degree)
    if deg < 0 or deg > g.sh_degree:
        raise ValueError(f"sh_degree {sh_degree} is outside 0..{g.sh_degree} (the model's SH degree)")
    view = camera if isinstance(camera, ViewParams) else ViewParams.from_camera(camera)
    projector = (lambda tile: project_model(g, deg, view, cfg, tile)) if g.n > 0 else None
    return _render(projector, view, background, cfg, capacity, layout, depth)


def render_arrays(ga: GaussianArrays | None, camera: Camera | ViewParams, background=(0.0, 0.0, 0.0),
                  cfg: RasterConfig = RasterConfig(), capacity: int | None = None,
                  layout: LaneLayout | None = None, depth: bool = True) -> RenderOutput:
    """Render activated Gaussians (``None`` or N = 0: an empty scene) for a camera or its prepared
    :class:`ViewParams`; gradients through Dr.Jit's AD of the projection. ``capacity``: see
    :func:`~mi_gaussians.raster.binning.bin_gaussians`; ``layout`` and ``depth``: see :func:`render`."""
    view = camera if isinstance(camera, ViewParams) else ViewParams.from_camera(camera)
    projector = (lambda tile: project(ga, view, cfg, tile)) if ga is not None and dr.width(ga.opacity) > 0 \
        else None
    return _render(projector, view, background, cfg, capacity, layout, depth)


def _render(projector, view: ViewParams, background, cfg: RasterConfig, capacity: int | None,
            layout: LaneLayout | None, depth: bool = True) -> RenderOutput:
    """Binning and blending of what ``projector(tile)`` projects (``tile``: the layout's (columns, rows); None: an
    empty scene)."""
    bg = _background(background)
    W, H = view.width, view.height
    if layout is None:
        layout = _blend_module.lane_layout()      # (looked up at each render: benchmarks and tests swap it)
    tiles_x, tiles_y = layout.tiles(W, H)

    if projector is not None:
        proj = projector(layout.tile)
        bins = bin_gaussians(proj.depth, proj.rect, proj.tile_count, tiles_x, tiles_y, capacity, proj.ellipse,
                             (view.width_f, view.height_f))
        radii = proj.radii
    else:
        proj = None
        bins = Bins(gaussian=dr.zeros(mi.UInt32, 0), tile_start=dr.zeros(mi.UInt32, tiles_x * tiles_y + 1),
                    n_instances=0, tiles_x=tiles_x, tiles_y=tiles_y)
        radii = dr.zeros(mi.Int32, 0)

    frame = make_frame(W, H, tiles_x, layout)
    stats = BlendStats()
    npix = W * H
    if capacity is None and bins.n_instances == 0:
        r, gch, b, dsum = (dr.zeros(mi.Float, npix) for _ in range(4))
        T = dr.full(mi.Float, 1.0, npix)
    else:
        r, gch, b, dsum, T = blend(proj.mean2d, proj.conic, proj.opacity, proj.color, proj.depth, bins, frame,
                                   cfg, stats, with_depth=depth)
    bgr, bgg, bgb = bg
    r, gch, b = r + T * bgr, gch + T * bgg, b + T * bgb
    alpha = 1.0 - T
    rgb = mi.TensorXf(dr.ravel(mi.Color3f(r, gch, b)), (H, W, 3))
    expected = None
    if depth:
        expected = mi.TensorXf(dr.select(alpha > 1e-12, dsum / fmax(alpha, 1e-12), 0.0), (H, W))
    return RenderOutput(rgb=rgb, alpha=mi.TensorXf(alpha, (H, W)), depth=expected,
                        radii=radii, n_instances=bins.n_instances, fits=bins.fits,
                        n_blended=bins.n_blended if bins.n_blended is not None else 0, _stats=stats,
                        _tile_counts=bins.tile_counts)
