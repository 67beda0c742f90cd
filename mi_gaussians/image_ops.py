"""Differentiable image operators in Dr.Jit: L1, SSIM (mean and map), D-SSIM and their fused weighted sum.

They are the building blocks of both the training loss (:mod:`mi_gaussians.optim.losses`) and the evaluation
metrics (:mod:`mi_gaussians.metrics`), so they sit in the base layer and import nothing of the package.

Images are ``mi.TensorXf`` of shape (H, W, C) (or (H, W)), any Dr.Jit variant (``llvm_ad_rgb``, ``cuda_ad_rgb``).

SSIM is exactly the reference 3DGS ``ssim`` (``utils/loss_utils.py``): a per-channel normalized Gaussian window
(``window`` taps, ``sigma``), applied as a "same"-size correlation with zero padding of ``window // 2``::

    mu1 = G * x,  mu2 = G * y,  s11 = G * (x x) - mu1^2,  s22 = G * (y y) - mu2^2,  s12 = G * (x y) - mu1 mu2
    map = ((2 mu1 mu2 + C1) (2 s12 + C2)) / ((mu1^2 + mu2^2 + C1) (s11 + s22 + C2)),   ssim = mean(map)

Derivative (a ``dr.CustomOp``: no AD graph through gathers, no atomics). With ``c_q = d map / d q``::

    c_xx = c_yy = -map / B2,   c_xy = 2 A1 / (B1 B2),   c_mu1 = 2 (mu2 (A2 - A1) / (B1 B2) + mu1 map (1/B2 - 1/B1))
    (c_mu2: swap 1 <-> 2;  A1 = 2 mu1 mu2 + C1, A2 = 2 s12 + C2, B1 = mu1^2 + mu2^2 + C1, B2 = s11 + s22 + C2)

and, a zero-padded blur with a symmetric kernel being self-adjoint, ``dL/dx = G*(g c_mu1) + 2 x G*(g c_xx) +
y G*(g c_xy)`` for an incoming map gradient g (``dL/dy`` likewise with ``c_mu2`` and x, y swapped). For the mean
SSIM, g is uniform.

Implementation (the walk itself: :mod:`mi_gaussians.image_walk`). ``G`` is separable; each 1D blur is a *walk*: a kernel whose lanes each move along one line of the
image (down a column, or along a row) over a block of pixels, keeping the last ``window - 1`` samples in the state of
a symbolic ``dr.while_loop`` (one small kernel; one load per sample instead of ``window``). On a CPU the cost is memory
traffic, so the layouts matter: images that a vertical walk reads are stored *tiled* (``_Planes``: columns of 16 floats
stored row after row, the quantities of one image set interleaved), so that a SIMD packet walking down a column reads
consecutive cache lines; horizontal walks read either layout and write the natural one.

- forward: horizontal walk over x, y (natural) -> the first pass of four blurs, of x, y, x^2 + y^2 and x y (tiled,
  interleaved; s11 and s22 enter the map only as their sum, so one blur serves both), and the L1 sum of
  the fused training loss; vertical walk -> SSIM map sums (and the map), plus the derivative maps when gradients are
  needed (tiled). For the loss (a uniform incoming gradient, which only scales them) on the CPU that walk also blurs
  the derivative maps down the columns (``image_walk._sweep_twice``), so they are never stored unblurred.
- backward: vertical walk over the derivative maps (the SSIM map's, whose incoming gradient weighs each pixel), then
  a horizontal walk that combines them with x and y into ``dL/dx`` (and ``dL/dy``) and adds the L1 term
  ``sign(x - y)`` of the fused loss.

The image size, window weights and C1/C2 are kernel literals (one compilation per resolution and window, ~0.2 s);
everything that depends on the images, including the incoming gradient and the loss weights, flows through arrays, so
calls on other images of the same size reuse the compiled kernels.

Measured (llvm_ad_rgb, 2-core AVX-512 CPU, 800 x 800 x 3): the training loss (``weighted_l1_ssim``, as
``mi_gaussians.optim.losses.photometric_loss`` calls it) forward + backward 21 ms (best) to 27 ms (median), of which
19 ms in four kernels; SSIM alone without gradients 10 ms. Since its vertical walks are one (2026-11-30): 15-16 ms in
three kernels against 17-18.5 for the four (400 x 400: 3.3-3.5 against 3.8-4.2 ms; 200 x 200: 1.1 against 1.3), the
same gradients bit for bit and the loss up to the order of its sum. Four blurs instead of the reference's five
(2026-11-30, fourteenth session): the loss and its gradient 0.93-0.97x at 400 x 400 and 0.95x at 200 x 200, equal to
float rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .drjit_utils import flat_mean
from .image_walk import _identity, _opaque, _Planes, _store, _sweep, _sweep_twice

@dataclass(frozen=True)
class SSIMParams:
    """The constants of SSIM: the Gaussian window's taps and sigma, and C1, C2. The defaults are the 3DGS reference's
    (:data:`REFERENCE_SSIM`), which the training loss and the metric use."""
    window: int = 11
    sigma: float = 1.5
    c1: float = 0.01 ** 2
    c2: float = 0.03 ** 2


REFERENCE_SSIM = SSIMParams()

#: BT.601 luma weights of linear RGB (gsplat's ``rgb2gray``): the bilateral grids' guidance, in training
#: (:mod:`mi_gaussians.optim.bilateral`) and in :func:`mi_gaussians.metrics.apply_bilateral`.
LUMA = (0.299, 0.587, 0.114)


# ---------------------------------------------------------------------------------------------------------- helpers
def gaussian_window(window: int = REFERENCE_SSIM.window, sigma: float = REFERENCE_SSIM.sigma) -> list[float]:
    """The reference's normalized 1D Gaussian: ``exp(-(k - window//2)^2 / (2 sigma^2))`` over k, divided by its sum."""
    if isinstance(window, bool) or not isinstance(window, int) or window < 1 or window % 2 != 1:
        raise ValueError(f"the SSIM window must be a positive odd number of pixels, got {window!r}")
    if not sigma > 0:
        raise ValueError(f"the SSIM window's sigma must be positive, got {sigma!r}")
    r = window // 2
    g = [math.exp(-((k - r) ** 2) / (2.0 * sigma * sigma)) for k in range(window)]
    s = sum(g)
    return [v / s for v in g]


def _flat(img, name: str):
    """(flat array, (H, W, C)) of an image tensor; typed errors for anything else."""
    if not dr.is_tensor_v(img):
        raise TypeError(f"{name} must be a Dr.Jit tensor (mi.TensorXf of shape (H, W, C)), got {type(img).__name__}")
    shape = tuple(img.shape)
    if len(shape) == 2:
        shape = shape + (1,)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"{name} must have shape (H, W, C) or (H, W), got {tuple(img.shape)}")
    return img.array, shape


def _pair(img, ref):
    x, shape = _flat(img, "img")
    y, shape_ref = _flat(ref, "ref")
    if shape != shape_ref:
        raise ValueError(f"img and ref must have the same shape, got {tuple(img.shape)} and {tuple(ref.shape)}")
    if type(x) is not type(y):
        raise TypeError(f"img and ref must be tensors of the same type, got {type(img).__name__} and "
                        f"{type(ref).__name__}")
    return x, y, shape


def _sign(d):
    """sign(d) with sign(0) = 0 (torch's ``abs`` derivative)."""
    return dr.select(d > 0, 1.0, dr.select(d < 0, -1.0, 0.0))


# which derivative maps exist: d map / d mu1, d mu2, d E[xx] (= d E[yy]), d E[xy]
_C_MU1, _C_MU2, _C_SQ, _C_XY = range(4)


def _needed_coefs(need_img: bool, need_ref: bool) -> list[int]:
    out = ([_C_MU1] if need_img else []) + ([_C_MU2] if need_ref else [])
    return out + [_C_SQ, _C_XY] if out else []


def _ssim_terms(b, c1: float, c2: float, coefs: list[int]):
    """The reference SSIM map and the requested derivative maps, from the four blurs: of x, y, x^2 + y^2 and x y.
    (The reference blurs x^2 and y^2 apart, but uses them only through sigma1^2 + sigma2^2 = G*(x^2 + y^2) - mu1^2 -
    mu2^2: one blur fewer, the same map up to float rounding.)"""
    mu1, mu2, e_sq, e12 = b
    mu1_sq, mu2_sq, mu1_mu2 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    mu_sq = mu1_sq + mu2_sq
    sigma12 = e12 - mu1_mu2
    a1, a2 = 2.0 * mu1_mu2 + c1, 2.0 * sigma12 + c2
    b1, b2 = mu_sq + c1, (e_sq - mu_sq) + c2
    s = (a1 * a2) / (b1 * b2)
    out = []
    if coefs:
        inv = dr.rcp(b1 * b2)                    # one division: 1/B1 = B2 inv, 1/B2 = B1 inv
        diff = (a2 - a1) * inv
        s_inv = s * inv
        d_b = s_inv * (b1 - b2)                  # map (1/B2 - 1/B1)
        for c in coefs:
            if c == _C_MU1:
                out.append(2.0 * (mu2 * diff + mu1 * d_b))
            elif c == _C_MU2:
                out.append(2.0 * (mu1 * diff + mu2 * d_b))
            elif c == _C_SQ:
                out.append(-s_inv * b1)          # -map / B2
            else:
                out.append(2.0 * a1 * inv)
    return s, out


def _forward(x, y, shape, weights, c1: float, c2: float, *, want_l1: bool = False, want_map: bool = False,
             coefs: tuple = (), coef_layout: str = "tiled"):
    """Two walks. Returns {"ssim_sum", "l1_sum" (when want_l1): Float (1,) sums over every pixel and channel;
    "map": natural flat map (when want_map); "coef": _Planes of the derivative maps ``coefs`` (in that order;
    tiled and interleaved, or one natural _Planes per map)}."""
    Float = type(x)
    h = _Planes.empty(Float, shape, "tiled", 4)

    def finish_h(blurred, centre, yy, pp, ok):
        return blurred, ([dr.abs(centre[0] - centre[1])] if want_l1 else [])

    l1_sum = _sweep([_Planes(x, "natural"), _Planes(y, "natural")], shape, 1, weights,
                    lambda a, b: (a, b, dr.fma(a, a, b * b), a * b), finish_h, [h], int(want_l1))
    if coef_layout == "blurred" and coefs:
        # the derivative maps blurred down the columns in the same walk, never stored unblurred (the first half of
        # the backward, done here: the loss's incoming gradient only scales them, in the backward's last walk)
        outs = [_Planes.empty(Float, shape, "tiled", len(coefs))]

        def finish_twice(blurred, centre, yy, pp, ok):
            s, cv = _ssim_terms(blurred, c1, c2, list(coefs))
            return cv, [s]

        (ssim_sum,) = _sweep_twice([h], shape, weights, _identity, finish_twice, outs, 1)
        out = {"ssim_sum": ssim_sum, "coef": outs}
        if want_l1:
            out["l1_sum"] = l1_sum[0]
        return out
    outs = [_Planes.empty(Float, shape, "natural")] if want_map else []
    if coefs:
        if coef_layout == "tiled":
            outs.append(_Planes.empty(Float, shape, "tiled", len(coefs)))
        else:
            outs += [_Planes.empty(Float, shape, "natural") for _ in coefs]

    def finish_v(blurred, centre, yy, pp, ok):
        s, cv = _ssim_terms(blurred, c1, c2, list(coefs))
        return ([s] if want_map else []) + cv, [s]

    (ssim_sum,) = _sweep([h], shape, 0, weights, _identity, finish_v, outs, 1)
    out = {"ssim_sum": ssim_sum}
    if want_l1:
        out["l1_sum"] = l1_sum[0]
    if want_map:
        out["map"] = outs[0].data
    if coefs:
        out["coef"] = outs[int(want_map):]
    return out


def _backward(x, y, coef: list, coef_ids: tuple, shape, weights, s_scale, l1_scale, need_img: bool,
              need_ref: bool, blurred: bool = False):
    """(dL/dx, dL/dy) (flat natural, None where not needed): blur the derivative maps ``coef`` (list of _Planes
    holding the maps ``coef_ids`` in order) vertically (unless ``blurred``: they were, in the forward's walk), then
    horizontally combined with x and y::

        dL/dx = s_scale (G*c_mu1 + 2 x G*c_sq + y G*c_xy) + l1_scale sign(x - y)     (l1_scale may be None)
        dL/dy = s_scale (G*c_mu2 + 2 y G*c_sq + x G*c_xy) - l1_scale sign(x - y)"""
    Float = type(x)
    n = len(coef_ids)
    if blurred:
        (v,) = coef
    else:
        v = _Planes.empty(Float, shape, "tiled", n)
        _sweep(coef, shape, 0, weights, _identity, _store, [v])

    def finish(b, centre, yy, pp, ok):
        d = dict(zip(coef_ids, b))
        idx = _Planes(x, "natural").indices(shape, yy, pp, dr.uint32_array_t(Float))[0]
        xv, yv = dr.gather(Float, x, idx, ok), dr.gather(Float, y, idx, ok)
        sg = _sign(xv - yv) if l1_scale is not None else None
        values = []
        if need_img:
            g = s_scale * (d[_C_MU1] + dr.fma(2.0 * xv, d[_C_SQ], yv * d[_C_XY]))
            values.append(g if sg is None else dr.fma(l1_scale, sg, g))
        if need_ref:
            g = s_scale * (d[_C_MU2] + dr.fma(2.0 * yv, d[_C_SQ], xv * d[_C_XY]))
            values.append(g if sg is None else g - l1_scale * sg)
        return values, ()

    outs = [_Planes.empty(Float, shape, "natural") for _ in range(int(need_img) + int(need_ref))]
    _sweep([v], shape, 1, weights, _identity, finish, outs)
    gi = outs[0].data if need_img else None
    gr = outs[-1].data if need_ref else None
    return gi, gr


# --------------------------------------------------------------------------------------------------- custom ops
def _combine(Float, r: dict, a: float, b: float, c: float, inv_n: float):
    """c + a * l1 + b * ssim from the sums of ``_forward`` (weights as opaque arrays: no recompilation per value)."""
    value = dr.fma(r["ssim_sum"], _opaque(Float, b * inv_n), _opaque(Float, c))
    if a != 0.0:
        value = dr.fma(r["l1_sum"], _opaque(Float, a * inv_n), value)
    return value


class _TwoImageOp(dr.CustomOp):
    """Shared reverse mode of the SSIM ops: ``_grads(g)`` gives the gradients w.r.t. the images x and y."""

    def backward(self):
        gi, gr = self._grads(self.grad_out())
        if gi is not None:
            self.set_grad_in("x", gi)
        if gr is not None:
            self.set_grad_in("y", gr)


class _LossOp(_TwoImageOp):
    """c + a * mean|x - y| + b * mean(SSIM map) (Python floats, a may be 0) with a hand-written derivative."""

    def eval(self, x, y, shape, weights, c1, c2, a, b, c, need_img, need_ref):
        self.x, self.y, self.shape, self.weights = x, y, shape, weights
        self.a, self.b, self.need_img, self.need_ref = a, b, need_img, need_ref
        self.inv_n = 1.0 / (shape[0] * shape[1] * shape[2])
        self.coef_ids = tuple(_needed_coefs(need_img, need_ref))
        # (the walk that blurs twice on the CPU, where it was measured; a GPU's walks are short, so there its lanes'
        # 4 R extra rows would cost more: not yet measured, the two walks stay)
        self.blurred = dr.backend_v(x) == dr.JitBackend.LLVM
        r = _forward(x, y, shape, weights, c1, c2, want_l1=a != 0.0, coefs=self.coef_ids,
                     coef_layout="blurred" if self.blurred else "tiled")
        self.coef = r["coef"]
        return _combine(type(x), r, a, b, c, self.inv_n)

    def _grads(self, g):
        """(dL/dx, dL/dy) for an incoming gradient g (1 entry)."""
        Float = type(self.x)
        g = Float(g)
        dr.make_opaque(g)
        # (the weights as opaque arrays too: ``g * python_float`` would compile one kernel per lambda)
        s_scale = g * _opaque(Float, self.b * self.inv_n)
        dr.make_opaque(s_scale)
        l1_scale = None
        if self.a != 0.0:
            l1_scale = g * _opaque(Float, self.a * self.inv_n)
            dr.make_opaque(l1_scale)
        return _backward(self.x, self.y, self.coef, self.coef_ids, self.shape, self.weights, s_scale, l1_scale,
                         self.need_img, self.need_ref, blurred=self.blurred)

    def forward(self):
        gi, gr = self._grads(1.0)
        d = 0.0
        if gi is not None:
            d = d + dr.sum(gi * self.grad_in("x"))
        if gr is not None:
            d = d + dr.sum(gr * self.grad_in("y"))
        self.set_grad_out(d)

    def name(self):
        return "ssim_loss"


class _SSIMMapOp(_TwoImageOp):
    """The SSIM map itself (flat, natural layout); the backward weights the derivative maps by the incoming
    per-pixel gradient before blurring them."""

    def eval(self, x, y, shape, weights, c1, c2, need_img, need_ref):
        self.x, self.y, self.shape, self.weights = x, y, shape, weights
        self.need_img, self.need_ref = need_img, need_ref
        self.coef_ids = tuple(_needed_coefs(need_img, need_ref))
        r = _forward(x, y, shape, weights, c1, c2, want_map=True, coefs=self.coef_ids, coef_layout="natural")
        self.coef = {i: p.data for i, p in zip(self.coef_ids, r["coef"])}
        dr.eval(r["map"], self.coef)
        return r["map"]

    def _grads(self, g):
        Float = type(self.x)
        g = Float(g)
        coef = [_Planes(self.coef[i] * g, "natural") for i in self.coef_ids]
        dr.eval([c.data for c in coef])
        return _backward(self.x, self.y, coef, self.coef_ids, self.shape, self.weights, _opaque(Float, 1.0), None,
                         self.need_img, self.need_ref)

    def forward(self):
        # d map = c_mu1 G*dx + c_mu2 G*dy + c_sq G*(2 x dx + 2 y dy) + c_xy G*(y dx + x dy)
        Float = type(self.x)
        n = dr.width(self.x)
        dx = Float(self.grad_in("x")) if self.need_img else dr.zeros(Float, n)
        dy = Float(self.grad_in("y")) if self.need_ref else dr.zeros(Float, n)
        srcs = [dx, dy, 2.0 * (self.x * dx + self.y * dy), self.y * dx + self.x * dy]
        dr.eval(srcs)
        h = _Planes.empty(Float, self.shape, "tiled", 4)
        _sweep([_Planes(s, "natural") for s in srcs], self.shape, 1, self.weights, _identity, _store, [h])
        blurred = [_Planes.empty(Float, self.shape, "natural") for _ in range(4)]
        _sweep([h], self.shape, 0, self.weights, _identity, _store, blurred)
        bdx, bdy, bsq, bxy = (b.data for b in blurred)
        out = self.coef[_C_SQ] * bsq + self.coef[_C_XY] * bxy
        if self.need_img:
            out = out + self.coef[_C_MU1] * bdx
        if self.need_ref:
            out = out + self.coef[_C_MU2] * bdy
        self.set_grad_out(out)

    def name(self):
        return "ssim_map"


# ------------------------------------------------------------------------------------------------------- public API
def weighted_l1_ssim(img: "mi.TensorXf", ref: "mi.TensorXf", l1_weight: float, ssim_weight: float,
                     offset: float = 0.0, params: SSIMParams = REFERENCE_SSIM) -> "mi.Float":
    """``offset + l1_weight * L1 + ssim_weight * SSIM`` -> Float (1,) (Python floats; ``l1_weight`` may be 0),
    through the fused kernels: the L1 term rides in the SSIM walks (its sum in the first forward walk, its
    ``sign(img - ref)`` derivative in the last backward walk), so value and gradient equal those of
    ``offset + l1_weight * l1(img, ref) + ssim_weight * ssim(img, ref)`` at the cost of SSIM alone. Differentiable
    with respect to ``img`` and/or ``ref``."""
    x, y, shape = _pair(img, ref)
    weights, c1, c2 = gaussian_window(params.window, params.sigma), float(params.c1), float(params.c2)
    a, b, c = float(l1_weight), float(ssim_weight), float(offset)
    need_img, need_ref = dr.grad_enabled(x), dr.grad_enabled(y)
    if need_img or need_ref:
        return dr.custom(_LossOp, x, y, shape, weights, c1, c2, a, b, c, need_img, need_ref)
    r = _forward(x, y, shape, weights, c1, c2, want_l1=a != 0.0)
    return _combine(type(x), r, a, b, c, 1.0 / (shape[0] * shape[1] * shape[2]))


def l1(img: "mi.TensorXf", ref: "mi.TensorXf") -> "mi.Float":
    """Mean absolute difference over every pixel and channel (img, ref: (H, W, C)) -> Float (1,). The derivative is
    sign(img - ref) / N with sign(0) = 0 (as torch's ``abs``); Dr.Jit's own ``abs`` would give 1."""
    x, y, _ = _pair(img, ref)
    d = x - y
    return flat_mean(d * dr.detach(_sign(d)))


def ssim(img: "mi.TensorXf", ref: "mi.TensorXf", params: SSIMParams = REFERENCE_SSIM) -> "mi.Float":
    """Mean SSIM of (H, W, C) images (the reference 3DGS ``ssim``: Gaussian window, zero padding) -> Float (1,),
    differentiable with respect to ``img`` and/or ``ref`` (whichever has gradients enabled)."""
    return weighted_l1_ssim(img, ref, l1_weight=0.0, ssim_weight=1.0, params=params)


def ssim_map(img: "mi.TensorXf", ref: "mi.TensorXf", params: SSIMParams = REFERENCE_SSIM) -> "mi.TensorXf":
    """The per-pixel, per-channel SSIM map (same shape as ``img``) whose mean is :func:`ssim` (differentiable)."""
    x, y, shape = _pair(img, ref)
    weights, c1, c2 = gaussian_window(params.window, params.sigma), float(params.c1), float(params.c2)
    need_img, need_ref = dr.grad_enabled(x), dr.grad_enabled(y)
    if need_img or need_ref:
        m = dr.custom(_SSIMMapOp, x, y, shape, weights, c1, c2, need_img, need_ref)
    else:
        m = _forward(x, y, shape, weights, c1, c2, want_map=True)["map"]
    return type(img)(m, tuple(img.shape))


def d_ssim(img: "mi.TensorXf", ref: "mi.TensorXf", params: SSIMParams = REFERENCE_SSIM) -> "mi.Float":
    """1 - SSIM (the structural term of the 3DGS loss) -> Float (1,)."""
    return weighted_l1_ssim(img, ref, l1_weight=0.0, ssim_weight=-1.0, offset=1.0, params=params)
