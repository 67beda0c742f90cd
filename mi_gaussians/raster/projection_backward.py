"""The projection of a model's raw parameter tables with a hand-written reverse mode, as one ``dr.CustomOp``.

:func:`project_model` is :func:`.projection.project` of ``GaussianArrays.from_gaussians(g, degree)``: the same forward
values (it runs that code), and gradients equal up to float rounding to those Dr.Jit's AD takes through it, which stays
the reference (``tests/test_projection_backward.py`` compares the two on every branch: culled, clamped to the guard
band, anti-aliased, every SH degree, colours clamped at 0, degenerate quaternions, a depth gradient). Why: on the CPU
the AD's reverse of the projection was the step's largest kernel after the blend's two (1,431 operations per Gaussian
on a 7k model of mi_objects), and the gradient tables it scattered into were zeroed first (a memset of the 45 SH
coefficients per Gaussian alone took 1 ms of a 34 ms step). Here the reverse recomputes the forward's intermediates
from the tables in one kernel and writes every element of each gradient table once, with plain scatters into
unzeroed buffers (the inactive SH bands get zeros): that kernel takes about what AD's did, the memsets are gone, and
the frozen step takes about 0.97x the time (docs/benchmarks/work_per_step.md).

The derivation is the reference's (``backward.cu``: ``computeColorFromSH``, ``computeCov2DCUDA``, ``computeCov3D``;
gsplat's ``fully_fused_projection`` backward) on our forward: the guard band clamps the normalized coordinates of the
Jacobian only (their gradient is zero where clamped), the projected mean is never clamped, culled Gaussians compute
with ``z = 1``, and every ``select`` passes its gradient exactly where the forward's does. A Gaussian that no output's
gradient reaches gets zeros, as from AD, which never scales a derivative by a zero gradient (its intermediates may
be NaN: a diverged pose correction makes the whole view so).

Used by :func:`.rasterize.render` when the model's tables or the view's pose (``R``, ``t``, ``center``: a pose
correction moves them differentiably, ``--pose-opt``) carry gradients and the intrinsics do not; their gradients are
the sums of each Gaussian's share. A Mitsuba ``ellipsoids`` shape's arrays (:func:`.rasterize.render_arrays`) go
through AD.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

from ..config import RasterConfig
from ..conventions import SH_C0
from ..drjit_utils import QUATERNION_FLOOR, normalization_vjp, quaternion_normalization, row_vectors, sigmoid
from ..model.gaussians import PARAMETER_NAMES, Gaussians
from ..model.sh import eval_sh_colors, sh_basis, sh_dir_grad
from .projection import (DIRECTION_FLOOR, GaussianArrays, Projected, ViewParams, covariance_2d, project,
                         view_directions)


class _Holder:
    """The projection's non-differentiable outputs, from ``eval`` to the caller (a plain class: ``dr.custom`` rebuilds
    dataclass arguments)."""

    proj: Projected | None = None


def _table(columns: list, n: int) -> "mi.Float":
    """A flat row-major table of ``n`` rows of ``len(columns)`` floats: every element written once (no zeroing
    pass), by plain scatters in ``Permute`` mode, which Dr.Jit compiles into one kernel (in another mode each scatter
    into the buffer would be a kernel of its own, and each would run the whole reverse pass again)."""
    if len(columns) == 1:
        return mi.Float(columns[0])
    out = dr.empty(mi.Float, n * len(columns))
    base = dr.arange(mi.UInt32, n) * len(columns)
    for j, c in enumerate(columns):
        dr.scatter(out, c, base + j, mode=dr.ReduceMode.Permute)
    return out


class _Inputs:
    """The raw parameters of a model as per-Gaussian arrays (detached), in the layout of :class:`Gaussians`."""

    def __init__(self, means, scales, rotations, opacities, sh_dc, sh_rest, degree: int, k_rest: int):
        self.p = row_vectors(mi.Point3f, means)[0]
        self.log_s = row_vectors(mi.Vector3f, scales)[0]
        self.q = row_vectors(mi.Vector4f, rotations)[0]
        self.logit = mi.Float(opacities)
        self.dc = row_vectors(mi.Vector3f, sh_dc)[0]
        self.rest = row_vectors(mi.Vector3f, sh_rest, k_rest, (degree + 1) ** 2 - 1) if k_rest else []
        self.degree = degree

    def arrays(self) -> GaussianArrays:
        return GaussianArrays(means=self.p, sigmas=dr.exp(self.log_s), quats=self.q, opacity=sigmoid(self.logit),
                              sh_dc=self.dc, sh_rest=self.rest, sh_degree=self.degree)


def projection_vjp(x: _Inputs, view: ViewParams, cfg: RasterConfig, g_mean2d, g_conic, g_opacity, g_color,
                   g_depth, view_grads: bool = False) -> dict:
    """The gradients of the raw parameters ``x`` from those of the projection's outputs: a dict of per-Gaussian
    arrays keyed like :class:`Gaussians` (``sh_rest``: a list over the active coefficients); with ``view_grads`` also
    each Gaussian's share of those of the view's ``R`` (a list of its rows), ``t`` and ``center``."""
    p, q = x.p, x.q
    s = dr.exp(x.log_s)
    W = view.R

    # ---- the forward's intermediates (projection.project's own)
    geo = covariance_2d(p, s, q, view, cfg)
    tcam, in_front, iz, u, v = geo.tcam, geo.in_front, geo.inv_z, geo.u, geo.v
    j00, j02, j11, j12, T0, T1, col = geo.j00, geo.j02, geo.j11, geo.j12, geo.T0, geo.T1, geo.col
    d0, d1, a0, a1 = geo.d0, geo.d1, geo.a0, geo.a1
    sig_a, cov_b, sig_c, cov_a, cov_c, inv_det = geo.sig_a, geo.cov_b, geo.sig_c, geo.cov_a, geo.cov_c, geo.inv_det
    fx, fy = view.fx, view.fy
    e = dr.exp(-x.logit)
    o = sigmoid(x.logit)                    # (its derivative e o^2, as AD takes it)

    # ---- colour: max(SH(dir) + 0.5, 0), dir = (p - centre) / |p - centre|
    dvec, n2, rn, dirs = view_directions(p, view)
    basis = sh_basis(dirs, x.degree)
    c = eval_sh_colors(x.dc, x.rest, dirs, x.degree, normalize=False, clamp=False)
    gc = mi.Vector3f(*[dr.select(c[i] < 0, 0.0, g_color[i]) for i in range(3)])
    g_dc = SH_C0 * gc
    g_rest = [basis[i + 1] * gc for i in range(len(x.rest))]
    g_dir = sh_dir_grad(dirs, x.degree, [dr.dot(gc, r) for r in x.rest])
    g_p = normalization_vjp(g_dir, dvec, n2, rn, DIRECTION_FLOOR)

    # ---- opacity and conic (a, b, c) = (cov_c, -cov_b, cov_a) / det
    g_inv_det = g_conic.x * cov_c - g_conic.y * cov_b + g_conic.z * cov_a
    g_cov_a, g_cov_b, g_cov_c = g_conic.z * inv_det, -g_conic.y * inv_det, g_conic.x * inv_det
    g_sig_a, g_sig_c = mi.Float(0.0), mi.Float(0.0)
    if cfg.antialiased:
        det_sigma = sig_a * sig_c - cov_b * cov_b
        ratio = det_sigma * inv_det
        positive = ratio > 0
        root = dr.sqrt(dr.select(positive, ratio, 1.0))
        comp = dr.select(positive, root, 0.0)
        g_o = g_opacity * comp
        g_ratio = dr.select(positive, (g_opacity * o) * 0.5 * dr.rcp(root), 0.0)
        g_det_sigma = g_ratio * inv_det
        g_inv_det = g_inv_det + g_ratio * det_sigma
        g_sig_a, g_sig_c = g_det_sigma * sig_c, g_det_sigma * sig_a
        g_cov_b = g_cov_b - 2.0 * cov_b * g_det_sigma
    else:
        g_o = g_opacity
    g_det = -g_inv_det * inv_det * inv_det
    g_sig_a = g_sig_a + g_cov_a + g_det * cov_c
    g_sig_c = g_sig_c + g_cov_c + g_det * cov_a
    g_cov_b = g_cov_b - 2.0 * cov_b * g_det
    g_logit = g_o * e * o * o

    # ---- (T M)(T M)^T with T = J W, M = R S
    g_a0 = [2.0 * g_sig_a * a0[k] + g_cov_b * a1[k] for k in range(3)]
    g_a1 = [2.0 * g_sig_c * a1[k] + g_cov_b * a0[k] for k in range(3)]
    g_log_s = mi.Vector3f(*[(g_a0[k] * d0[k] + g_a1[k] * d1[k]) * s[k] for k in range(3)])
    h0 = [g_a0[k] * s[k] for k in range(3)]
    h1 = [g_a1[k] * s[k] for k in range(3)]
    g_T0 = h0[0] * col[0] + h0[1] * col[1] + h0[2] * col[2]
    g_T1 = h1[0] * col[0] + h1[1] * col[1] + h1[2] * col[2]
    G = [h0[k] * T0 + h1[k] * T1 for k in range(3)]        # G[k][i]: the gradient of Rq[i][k]
    g_q = _quaternion_vjp(q, [[G[k][i] for k in range(3)] for i in range(3)])

    # ---- the Jacobian (through the clamped coordinates) and the mean
    g_j00, g_j02 = dr.dot(g_T0, W[0]), dr.dot(g_T0, W[2])
    g_j11, g_j12 = dr.dot(g_T1, W[1]), dr.dot(g_T1, W[2])
    g_xu = dr.select(geo.u_free, -fx * iz * g_j02, 0.0)
    g_xv = dr.select(geo.v_free, -fy * iz * g_j12, 0.0)
    g_iz = fx * (g_j00 - u * g_j02) + fy * (g_j11 - v * g_j12)
    g_tx = (g_xu + g_mean2d.x * fx) * iz
    g_ty = (g_xv + g_mean2d.y * fy) * iz
    g_iz = g_iz + (g_xu + g_mean2d.x * fx) * tcam.x + (g_xv + g_mean2d.y * fy) * tcam.y
    g_tz = g_depth + dr.select(in_front, -g_iz * iz * iz, 0.0)
    g_t = mi.Vector3f(g_tx, g_ty, g_tz)
    g_dir_p = g_p
    g_p = g_p + g_t.x * W[0] + g_t.y * W[1] + g_t.z * W[2]      # W^T g_t (W[i]: the rows)
    out = {"means": g_p, "scales": g_log_s, "rotations": g_q, "opacities": g_logit, "sh_dc": g_dc, "sh_rest": g_rest}
    if view_grads:
        # per Gaussian: through t_cam = W p + t, the rows of W in T0 and T1, and dir = p - centre
        rows = [g_t[i] * p + (j00 * g_T0 if i == 0 else j11 * g_T1 if i == 1 else j02 * g_T0 + j12 * g_T1)
                for i in range(3)]
        out["R"], out["t"], out["center"] = rows, g_t, -g_dir_p
    # A Gaussian no output's gradient reaches gets zeros, as from AD, which scales no derivative by a zero gradient:
    # its intermediates may be infinite or NaN (a non-finite view, a culled or degenerate Gaussian), and 0 * NaN is NaN
    reached = ((g_mean2d.x != 0) | (g_mean2d.y != 0) | (g_conic.x != 0) | (g_conic.y != 0) | (g_conic.z != 0)
               | (g_opacity != 0) | (g_color.x != 0) | (g_color.y != 0) | (g_color.z != 0) | (g_depth != 0))
    return {k: [_only(reached, r) for r in v] if isinstance(v, list) else _only(reached, v) for k, v in out.items()}


def _only(mask, v):
    """``v`` where ``mask``, zeros elsewhere (any Dr.Jit vector or float array)."""
    return dr.select(mask, v, type(v)(0.0))


def _quaternion_vjp(q, G) -> "mi.Vector4f":
    """The gradient of the (w, x, y, z) quaternion ``q`` (any norm) from ``G[i][k]``, that of entry (i, k) of
    :func:`~mi_gaussians.drjit_utils.quaternion_to_matrix` (which normalizes ``q`` first)."""
    n2, r = quaternion_normalization(q)
    w, x, y, z = q.x * r, q.y * r, q.z * r, q.w * r
    gw = 2.0 * (z * (G[1][0] - G[0][1]) + y * (G[0][2] - G[2][0]) + x * (G[2][1] - G[1][2]))
    gx = 2.0 * (y * (G[0][1] + G[1][0]) + z * (G[0][2] + G[2][0]) + w * (G[2][1] - G[1][2])
                - 2.0 * x * (G[1][1] + G[2][2]))
    gy = 2.0 * (x * (G[0][1] + G[1][0]) + z * (G[1][2] + G[2][1]) + w * (G[0][2] - G[2][0])
                - 2.0 * y * (G[0][0] + G[2][2]))
    gz = 2.0 * (x * (G[0][2] + G[2][0]) + y * (G[1][2] + G[2][1]) + w * (G[1][0] - G[0][1])
                - 2.0 * z * (G[0][0] + G[1][1]))
    g = mi.Vector4f(gw, gx, gy, gz)
    return normalization_vjp(g, q, n2, r, QUATERNION_FLOOR)


class ProjectOp(dr.CustomOp):
    """Differentiable projection of raw tables: outputs (mean2d, conic, opacity, colour, depth); see the module. The
    view's rotation, translation and centre are inputs of their own (a pose correction differentiates them)."""

    def eval(self, means, scales, rotations, opacities, sh_dc, sh_rest, R, t, center, view, cfg, degree, k_rest,
             tile, enabled, holder):
        self.x = _Inputs(means, scales, rotations, opacities, sh_dc, sh_rest, degree, k_rest)
        self.view = dataclasses.replace(view, R=R, t=t, center=center)
        self.cfg, self.k_rest, self.enabled = cfg, k_rest, enabled
        proj = project(self.x.arrays(), self.view, cfg, tile)
        holder.proj = proj
        return proj.mean2d, proj.conic, proj.opacity, proj.color, proj.depth

    def forward(self):
        raise NotImplementedError("mi_gaussians: forward-mode derivatives of the projection are not implemented; "
                                  "use reverse mode (dr.backward)")

    def backward(self):
        g_mean2d, g_conic, g_opacity, g_color, g_depth = self.grad_out()
        view_on = self.enabled[len(PARAMETER_NAMES):]
        g = projection_vjp(self.x, self.view, self.cfg, mi.Vector2f(g_mean2d), mi.Vector3f(g_conic),
                           mi.Float(g_opacity), mi.Vector3f(g_color), mi.Float(g_depth), view_grads=any(view_on))
        n = dr.width(self.x.logit)
        zero = dr.zeros(mi.Float, n)
        rest = [c for v in g["sh_rest"] for c in (v.x, v.y, v.z)]
        columns = {"means": list(g["means"]), "scales": list(g["scales"]), "rotations": list(g["rotations"]),
                   "opacities": [g["opacities"]], "sh_dc": list(g["sh_dc"]),
                   "sh_rest": rest + [zero] * (3 * self.k_rest - len(rest))}
        tables = {name: _table(columns[name], n)
                  for name, on in zip(PARAMETER_NAMES, self.enabled) if on and columns[name]}
        # the view's gradients are sums of each Gaussian's share, evaluated with the tables and reduced after
        shares = {"R": [c for row in g["R"] for c in row], "t": list(g["t"]), "center": list(g["center"])} \
            if any(view_on) else {}
        shares = {name: shares[name] for name, on in zip(_VIEW, view_on) if on}
        dr.eval(tables, shares)  # one kernel: each table evaluated on its own would run the whole reverse pass again
        for name, table in tables.items():
            self.set_grad_in(name, table)
        for name, share in shares.items():
            sums = [dr.sum(c) for c in share]
            if name == "R":
                self.set_grad_in(name, mi.Matrix3f([[sums[3 * i + j] for j in range(3)] for i in range(3)]))
            else:
                self.set_grad_in(name, (mi.Vector3f if name == "t" else mi.Point3f)(*sums))

    def name(self):
        return "mi_gaussians.Project"


_VIEW = ("R", "t", "center")


def uses_hand_written_backward(g: Gaussians, view: ViewParams) -> bool:
    """Whether :func:`project_model` takes the hand-written reverse mode: the model's tables or the view's pose
    (``R``, ``t``, ``center``) carry gradients, and the intrinsics do not."""
    if dr.grad_enabled((view.fx, view.fy, view.cx, view.cy, view.width_f, view.height_f)):
        return False
    return dr.grad_enabled((tuple(getattr(g, t) for t in PARAMETER_NAMES), view.R, view.t, view.center))


def project_model(g: Gaussians, degree: int, view: ViewParams, cfg: RasterConfig, tile: tuple) -> Projected:
    """``project(GaussianArrays.from_gaussians(g, degree), view, cfg, tile)``, with the hand-written reverse
    mode of :class:`ProjectOp` where :func:`uses_hand_written_backward`."""
    if not uses_hand_written_backward(g, view):
        return project(GaussianArrays.from_gaussians(g, degree), view, cfg, tile)
    tables = [getattr(g, t) for t in PARAMETER_NAMES]
    k_rest = int(g.sh_rest.shape[1]) if len(g.sh_rest.shape) == 3 else 0
    holder = _Holder()
    enabled = tuple(bool(dr.grad_enabled(t)) for t in tables) + tuple(
        bool(dr.grad_enabled(getattr(view, v))) for v in _VIEW)
    mean2d, conic, opacity, color, depth = dr.custom(
        ProjectOp, *[t.array for t in tables], view.R, view.t, view.center, view, cfg, int(degree), k_rest,
        (int(tile[0]), int(tile[1])), enabled, holder)
    proj = holder.proj
    return Projected(mean2d=mean2d, conic=conic, opacity=opacity, color=color, depth=depth, rect=proj.rect,
                     tile_count=proj.tile_count, radii=proj.radii, ellipse=proj.ellipse)
