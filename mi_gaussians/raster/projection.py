"""EWA projection of 3D Gaussians (plain Dr.Jit arithmetic, differentiable by Dr.Jit's AD).

Per Gaussian: activations, 3D covariance R S S^T R^T, camera-space mean, the Jacobian with the reference's guard
band, the dilated 2D covariance and its conic, an opacity-aware screen footprint, the tile rectangle, the
view-dependent colour and the depth. Everything is computed for all N Gaussians; culled ones get an empty tile
rectangle (and radius 0), so the blending never sees them and their gradients are zero.

Guard band: the reference clamps ``t_x / t_z`` to ``1.3 * tan(fov_x / 2)``, which assumes a centred principal point.
We clamp the projected mean to the pixel interval ``[-0.15 W, 1.15 W]`` (and likewise in y); for ``cx = W / 2`` this is
the same interval, and it stays 30 % beyond the image edge on both sides for an off-centre principal point.

Anti-aliasing (``RasterConfig.antialiased``, Mip-Splatting's 2D filter as gsplat's ``antialiased`` mode and the
2024 reference's ``--antialiasing``): the dilation stays a low-pass filter of the footprint, and the opacity is scaled
by ``sqrt(det(S) / det(S + dilation I))`` with ``S`` the undilated 2D covariance, so a Gaussian much smaller than a
pixel keeps its energy instead of growing into a 0.3-pixel blob of full opacity. Everything downstream (footprint,
blending) sees the scaled opacity.

Footprint: a Gaussian of opacity ``o`` reaches alpha >= alpha_min exactly where ``d^T conic d <= 2 ln(o / alpha_min)``;
the axis-aligned box of that ellipse is ``|dx| <= sqrt(2 ln(o / alpha_min) * Sigma_xx)`` and likewise in y. Covering
that box (with a tiny safety margin) makes the image independent of the tile grid, unlike the reference's 3-sigma
circle, and is tighter for faint and for elongated Gaussians; with ``RasterConfig.footprint = "ellipse"`` binning
then keeps only the box's tiles the ellipse reaches (:mod:`.footprint`). ``radii`` keeps the reference definition
``ceil(3 sqrt(lambda_max))``: densification counts a Gaussian as seen where it is > 0, and its optional screen-size
prune compares it with the image size.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import RasterConfig
from ..data.camera import Camera
from ..drjit_utils import fclamp, floored_normalization, fmax, quaternion_to_matrix, row_vectors, sigmoid
from ..model.gaussians import Gaussians
from ..model.sh import eval_sh_colors, gather_sh_coeffs
from .blend import TILE
from .footprint import Ellipse, box


@dataclass(frozen=True)
class ViewParams:
    """Per-view constants as *opaque* Dr.Jit scalars, so one compiled kernel serves every camera.

    Python floats would be baked into kernels as literals and every new view would recompile."""

    R: "mi.Matrix3f"          # world -> camera rotation
    t: "mi.Vector3f"          # world -> camera translation
    center: "mi.Point3f"      # camera centre in world space
    fx: "mi.Float"
    fy: "mi.Float"
    cx: "mi.Float"
    cy: "mi.Float"
    width_f: "mi.Float"
    height_f: "mi.Float"
    width: int                # image size (host-side: sets launch sizes)
    height: int

    @classmethod
    def from_camera(cls, cam: Camera) -> "ViewParams":
        def op(v):
            return dr.opaque(mi.Float, float(v))

        w2c = np.asarray(cam.world_to_camera, dtype=np.float64)
        R = mi.Matrix3f([[op(w2c[i, j]) for j in range(3)] for i in range(3)])
        t = mi.Vector3f(op(w2c[0, 3]), op(w2c[1, 3]), op(w2c[2, 3]))
        c = cam.center
        return cls(R=R, t=t, center=mi.Point3f(op(c[0]), op(c[1]), op(c[2])), fx=op(cam.fx), fy=op(cam.fy),
                   cx=op(cam.cx), cy=op(cam.cy), width_f=op(cam.width), height_f=op(cam.height),
                   width=cam.width, height=cam.height)


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities (size N). AD-tracked: mean2d, conic, opacity, color, depth."""

    mean2d: "mi.Point2f"      # pixel coordinates of the projected mean
    conic: "mi.Vector3f"      # inverse of the dilated 2D covariance: (a, b, c) of [[a, b], [b, c]]
    opacity: "mi.Float"       # sigmoid(opacity logit), times the compensation when anti-aliased
    color: "mi.Color3f"       # max(SH(dir) + 0.5, 0)
    depth: "mi.Float"         # camera-space z
    rect: tuple               # (tx0, ty0, tx1, ty1) tile rectangle, inclusive, mi.Int32 (detached)
    tile_count: "mi.UInt32"   # number of tiles of the rectangle (0 when culled)
    radii: "mi.Int32"         # reference radius ceil(3 sqrt(lambda_max)) in pixels, 0 when culled
    ellipse: Ellipse | None = None   # footprint 'ellipse': the test of the rectangle's tiles it reaches (binning)


@dataclass
class GaussianArrays:
    """Activated per-Gaussian inputs of the projection (size N), AD-tracked; built from ``Gaussians`` or from
    a Mitsuba ``ellipsoids`` shape."""

    means: "mi.Point3f"
    sigmas: "mi.Vector3f"          # standard deviations (exp of the log-scales)
    quats: "mi.Vector4f"           # (w, x, y, z), any norm
    opacity: "mi.Float"            # in (0, 1)
    sh_dc: "mi.Vector3f"
    sh_rest: list                  # (degree + 1)^2 - 1 mi.Vector3f, band order, active bands only
    sh_degree: int

    @classmethod
    def from_gaussians(cls, g: Gaussians, sh_degree: int) -> "GaussianArrays":
        # Every element is read once: the reverse mode writes the gradients with plain scatters (row_vectors)
        dc, rest = gather_sh_coeffs(g.sh_dc, g.sh_rest, sh_degree)
        return cls(means=row_vectors(mi.Point3f, g.means.array)[0],
                   sigmas=dr.exp(row_vectors(mi.Vector3f, g.scales.array)[0]),
                   quats=row_vectors(mi.Vector4f, g.rotations.array)[0],
                   opacity=sigmoid(g.opacities.array),
                   sh_dc=dc, sh_rest=rest, sh_degree=sh_degree)


def _compensation(det_sigma, inv_det):
    """Mip-Splatting's opacity factor sqrt(det(S) / det(S + dilation I)) (gsplat: ``max(0, ...)`` under the root);
    its gradient is zero where the factor is 0 (a degenerate footprint), not the infinite slope of sqrt at 0."""
    ratio = det_sigma * inv_det
    positive = ratio > 0
    return dr.select(positive, dr.sqrt(dr.select(positive, ratio, 1.0)), 0.0)


def guard_limits(view: ViewParams, cfg: RasterConfig) -> tuple:
    """(x0, x1, y0, y1): the interval the Jacobian clamps the normalized coordinates t_x / t_z and t_y / t_z to, the
    image widened by the guard band on each side (see the module docstring)."""
    band = 0.5 * (cfg.guard_band - 1.0)   # 0.15: the reference's 1.3 tan(fov / 2) band, as a fraction of the size
    return ((-band * view.width_f - view.cx) / view.fx, ((1.0 + band) * view.width_f - view.cx) / view.fx,
            (-band * view.height_f - view.cy) / view.fy, ((1.0 + band) * view.height_f - view.cy) / view.fy)


@dataclass
class Covariance2D:
    """The projection's intermediates up to the dilated 2D covariance (one home for the forward and the hand-written
    reverse mode of :mod:`.projection_backward`): camera-space mean, culling, the Jacobian with its guard band (``u``,
    ``v`` the clamped normalized coordinates, ``u_free``/``v_free`` where the clamp passes their gradient), ``T = J W``
    (rows ``T0``, ``T1``), the rotation's columns ``col``, ``d0[k] = T0 . col[k]`` (``d1`` likewise), ``a0 = d0 s``,
    ``a1 = d1 s``, the undilated (``sig_a``, ``cov_b``, ``sig_c``) and dilated (``cov_a``, ``cov_b``, ``cov_c``)
    entries, the determinant and its inverse."""

    tcam: object
    in_front: object
    inv_z: object
    u: object
    v: object
    u_free: object
    v_free: object
    j00: object
    j02: object
    j11: object
    j12: object
    T0: object
    T1: object
    col: list
    d0: list
    d1: list
    a0: list
    a1: list
    sig_a: object
    cov_b: object
    sig_c: object
    cov_a: object
    cov_c: object
    det: object
    inv_det: object


def covariance_2d(means, sigmas, quats, view: ViewParams, cfg: RasterConfig) -> Covariance2D:
    """EWA: ``(J W R S)(J W R S)^T`` plus the dilation, with everything it is made of (:class:`Covariance2D`)."""
    # Camera space
    tcam = view.R @ means + view.t
    tz = tcam.z
    in_front = dr.detach(tz) > cfg.near_plane
    # culled Gaussians use z = 1 in the arithmetic below so nothing overflows into NaN gradients
    inv_z = dr.rcp(dr.select(in_front, tz, 1.0))

    # Jacobian with the guard band (clamped normalized coordinates; see the module docstring)
    lim_x0, lim_x1, lim_y0, lim_y1 = guard_limits(view, cfg)
    xu, xv = tcam.x * inv_z, tcam.y * inv_z
    u = fclamp(xu, lim_x0, lim_x1)
    v = fclamp(xv, lim_y0, lim_y1)
    j00 = view.fx * inv_z
    j02 = -view.fx * u * inv_z
    j11 = view.fy * inv_z
    j12 = -view.fy * v * inv_z

    # T = J W (2 x 3), M = R S (3 x 3), Sigma2D = (T M)(T M)^T
    Rq = quaternion_to_matrix(quats)
    W = view.R
    T0 = j00 * W[0] + j02 * W[2]      # rows of J W (W[i] is the i-th row of the view rotation)
    T1 = j11 * W[1] + j12 * W[2]
    # columns of M = R S: M[:, k] = R[:, k] * s_k; (T M)_{rk} = dot(T_r, R[:, k]) * s_k
    col = [mi.Vector3f(Rq[0][k], Rq[1][k], Rq[2][k]) for k in range(3)]
    d0 = [dr.dot(T0, col[k]) for k in range(3)]
    d1 = [dr.dot(T1, col[k]) for k in range(3)]
    a0 = [d0[k] * sigmas[k] for k in range(3)]
    a1 = [d1[k] * sigmas[k] for k in range(3)]
    sig_a = a0[0] * a0[0] + a0[1] * a0[1] + a0[2] * a0[2]
    cov_b = a0[0] * a1[0] + a0[1] * a1[1] + a0[2] * a1[2]
    sig_c = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2]
    cov_a = sig_a + cfg.dilation
    cov_c = sig_c + cfg.dilation
    det = cov_a * cov_c - cov_b * cov_b
    return Covariance2D(tcam=tcam, in_front=in_front, inv_z=inv_z, u=u, v=v,
                        u_free=(xu > lim_x0) & (xu < lim_x1), v_free=(xv > lim_y0) & (xv < lim_y1),
                        j00=j00, j02=j02, j11=j11, j12=j12, T0=T0, T1=T1, col=col, d0=d0, d1=d1, a0=a0, a1=a1,
                        sig_a=sig_a, cov_b=cov_b, sig_c=sig_c, cov_a=cov_a, cov_c=cov_c, det=det,
                        inv_det=dr.rcp(det))


#: |mean - camera centre|^2 is floored here before its inverse square root (a Gaussian at the camera centre)
DIRECTION_FLOOR = 1e-30


def view_directions(means, view: ViewParams) -> tuple:
    """The SH colour's view direction and what it is made of: (``d = mean - camera centre``, ``|d|^2``, ``1 / |d|``
    (``|d|^2`` floored at :data:`DIRECTION_FLOOR`), ``d / |d|``)."""
    d = means - view.center
    n2, rn = floored_normalization(d, DIRECTION_FLOOR)
    return d, n2, rn, d * rn


def project(ga: GaussianArrays, view: ViewParams, cfg: RasterConfig, tile: tuple = (TILE, TILE)) -> Projected:
    """Project activated Gaussians for a view; the tile rectangles are those of a grid of tiles of ``tile`` =
    (columns, rows) pixels (the blend's :attr:`~.blend.LaneLayout.tile`)."""
    means, opacity = ga.means, ga.opacity
    geo = covariance_2d(means, ga.sigmas, ga.quats, view, cfg)
    tcam, tz, in_front, inv_z = geo.tcam, geo.tcam.z, geo.in_front, geo.inv_z
    sig_a, cov_b, sig_c, cov_a, cov_c, det, inv_det = geo.sig_a, geo.cov_b, geo.sig_c, geo.cov_a, geo.cov_c, geo.det, \
        geo.inv_det
    conic = mi.Vector3f(cov_c * inv_det, -cov_b * inv_det, cov_a * inv_det)
    if cfg.antialiased:
        opacity = opacity * _compensation(sig_a * sig_c - cov_b * cov_b, inv_det)

    mean2d = mi.Point2f(view.fx * tcam.x * inv_z + view.cx, view.fy * tcam.y * inv_z + view.cy)

    # Colour from SH (view direction from the camera centre to the mean)
    dirs = view_directions(means, view)[3]
    color = mi.Color3f(eval_sh_colors(ga.sh_dc, ga.sh_rest, dirs, ga.sh_degree, normalize=False))

    # ---- footprint, culling, tile rectangle (no gradients needed)
    with dr.suspend_grad():
        o = dr.detach(opacity)
        a, b, c, dt = dr.detach(cov_a), dr.detach(cov_b), dr.detach(cov_c), dr.detach(det)
        k2 = 2.0 * dr.log(o * (1.0 / cfg.alpha_min))
        valid = in_front & (dt > 0) & (k2 >= 0)
        rect, count, valid, ellipse = box(dr.detach(mean2d), a, b, c, dt, k2, valid, view.width_f, view.height_f,
                                          ellipse=cfg.footprint == "ellipse", tile=tile)
        mid = 0.5 * (a + c)
        lam = mid + dr.sqrt(fmax(mid * mid - dt, 0.1))
        radii = dr.select(valid, mi.Int32(dr.ceil(3.0 * dr.sqrt(lam))), 0)

    # One kernel for every output: evaluated where each is first needed (the depth sort, the tile counts, the
    # rectangles, the ellipse test, the blend's packed features), each would re-run the projection from the gathers
    footprint = [getattr(ellipse, f.name) for f in dataclasses.fields(ellipse) if f.name != "tile"] \
        if ellipse is not None else []
    dr.eval(mean2d, conic, opacity, color, tz, rect, count, radii, footprint)
    return Projected(mean2d=mean2d, conic=conic, opacity=opacity, color=color, depth=tz,
                     rect=rect, tile_count=count, radii=radii, ellipse=ellipse)
