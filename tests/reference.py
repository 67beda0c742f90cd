"""An independent, deliberately plain NumPy reference renderer for 3D Gaussian Splatting (test oracle).

It implements the forward model of the reference CUDA rasterizer of Kerbl et al. 2023 (``diff-gaussian-rasterization``)
per pixel, with no tiles, no radii and no bounding boxes: every pixel looks at every non-culled Gaussian, front to back.
It shares no code with ``mi_gaussians.raster`` (it must stay an independent oracle) and only duck-types the camera
(``width, height, fx, fy, cx, cy, world_to_camera``), so it needs nothing from the package.

The model, exactly (all arithmetic in ``dtype``; float64 unless asked otherwise):

Per Gaussian (raw parameters -> screen-space quantities)
    q = rotation / |q| (w, x, y, z);  R(q) the usual rotation matrix;  S = diag(exp(scales));  Sigma = R S S^T R^T
    t = W_rot @ mean + W_trans (world_to_camera, OpenCV axes);  culled when t_z <= 0.2 (near plane)
    guard band: u = clamp(t_x / t_z, (-0.15 W - cx) / fx, (1.15 W - cx) / fx), v likewise with H, cy, fy
                (= the reference's +-1.3 tan(fov / 2) when the principal point is centred)
    J = [[fx / t_z, 0, -fx u / t_z], [0, fy / t_z, -fy v / t_z]]
    Sigma2D = J W_rot Sigma W_rot^T J^T + 0.3 I = [[a, b], [b, c]];  culled when det = a c - b^2 <= 0
    conic = Sigma2D^-1 = (c, -b, a) / det
    mean2D = (fx t_x / t_z + cx, fy t_y / t_z + cy)      (unclamped t; pixel (i, j) is sampled at (i + 0.5, j + 0.5))
    opacity = sigmoid(logit);  depth = t_z
    anti-aliased (antialiased=True): opacity *= sqrt(max(det(S) / det, 0)) with S = Sigma2D - 0.3 I (undilated)
    colour = max(SH(normalize(mean - camera centre)) + 0.5, 0) with the reference's constants and signs
Per pixel p (front to back over the non-culled Gaussians, sorted by depth with a STABLE sort: ties keep index order)
    d = mean2D - p;  power = -0.5 (conic_a dx^2 + conic_c dy^2) - conic_b dx dy;  skip when power > 0
    alpha = min(0.99, opacity exp(power));  skip when alpha < 1/255
    if T (1 - alpha) < 1e-4: stop (this Gaussian does not contribute)
    C += colour alpha T;  D += depth alpha T;  T *= 1 - alpha
Outputs
    rgb = C + T background;  alpha = 1 - T;  depth = D / (1 - T) where 1 - T > 0, else 0 (expected depth)

Public API
    render_reference(params, camera, background=(0, 0, 0), sh_degree=None, dtype=np.float64, antialiased=False) -> dict
    fd_gradients(params, camera, weights, background=(0, 0, 0), sh_degree=None, eps=1e-6, names=None,
                 index_subset=None, return_unreliable=False, antialiased=False) -> dict name -> array (or (grads,
                 unreliable))
    plus the building blocks (quaternion_to_matrix, covariance_3d, sh_basis, sh_to_color, preprocess, composite,
    composite_batch, depth_order, render_losses).
"""

from __future__ import annotations

import math

import numpy as np

# ---------------------------------------------------------------------------------------------- constants
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

NEAR_PLANE = 0.2        # culled when camera-space z <= NEAR_PLANE
DILATION = 0.3          # added to the diagonal of the 2D covariance (low-pass filter)
GUARD_BAND = 0.15       # the Jacobian clamps the projected mean to [-0.15 W, 1.15 W] x [-0.15 H, 1.15 H] (pixels)
ALPHA_MAX = 0.99        # alpha = min(ALPHA_MAX, opacity * exp(power))
ALPHA_MIN = 1.0 / 255.0  # skipped when alpha < ALPHA_MIN
T_MIN = 1e-4            # stop before the Gaussian that would bring T below T_MIN

PARAM_NAMES = ("means", "scales", "rotations", "opacities", "sh_dc", "sh_rest")
OUTPUT_NAMES = ("rgb", "alpha", "depth")


# ---------------------------------------------------------------------------------------------- parameters
def sh_degree_from_count(k: int) -> int:
    """SH degree d from the number of coefficients per channel K = (d + 1)^2 (d in 0..3)."""
    d = int(round(math.sqrt(k))) - 1
    if d < 0 or d > 3 or (d + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients per channel is not (d + 1)^2 for a degree d in 0..3")
    return d


def as_params(params: dict, dtype=np.float64) -> dict:
    """Validated copies of the raw parameters in ``dtype`` with canonical shapes (sh_rest may be absent: degree 0)."""
    dt = np.dtype(dtype)
    means = np.asarray(params["means"], dtype=dt).reshape(-1, 3)
    n = means.shape[0]
    out = {
        "means": means.copy(),
        "scales": np.asarray(params["scales"], dtype=dt).reshape(n, 3).copy(),
        "rotations": np.asarray(params["rotations"], dtype=dt).reshape(n, 4).copy(),
        "opacities": np.asarray(params["opacities"], dtype=dt).reshape(n).copy(),
        "sh_dc": np.asarray(params["sh_dc"], dtype=dt).reshape(n, 3).copy(),
    }
    rest = params.get("sh_rest")
    if rest is None:
        rest = np.zeros((n, 0, 3), dtype=dt)
    rest = np.asarray(rest, dtype=dt)
    if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3:
        raise ValueError(f"sh_rest: expected shape ({n}, K-1, 3), got {rest.shape}")
    sh_degree_from_count(rest.shape[1] + 1)
    out["sh_rest"] = rest.copy()
    return out


def sigmoid(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        return 1.0 / (1.0 + np.exp(-x))


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) unnormalized (w, x, y, z) -> (N, 3, 3) rotation matrices. A zero quaternion is an error."""
    q = np.asarray(q)
    norm = np.sqrt(np.sum(q * q, axis=-1))
    if np.any(norm == 0) or not np.all(np.isfinite(norm)):
        raise ValueError("rotations: a quaternion has zero (or non-finite) norm; its rotation is undefined")
    w, x, y, z = (q / norm[:, None]).T
    one = np.ones_like(w)
    return np.stack([
        np.stack([one - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), one - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), one - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def covariance_3d(scales: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Sigma = R S S^T R^T, (N, 3, 3), from log-sigmas (N, 3) and unnormalized quaternions (N, 4)."""
    M = quaternion_to_matrix(rotations) * np.exp(scales)[:, None, :]  # R S (scales each column)
    return M @ np.swapaxes(M, -1, -2)


# ---------------------------------------------------------------------------------------------- SH
def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """The reference's real SH basis (constants and signs of computeColorFromSH): (N, 3) unit dirs -> (N, (d+1)^2)."""
    x, y, z = np.asarray(dirs).T
    one = np.ones_like(x)
    cols = [SH_C0 * one]
    if degree > 0:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        cols += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree > 2:
        cols += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                 SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                 SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return np.stack(cols, axis=-1).astype(np.asarray(dirs).dtype, copy=False)


def sh_to_color(sh_dc: np.ndarray, sh_rest: np.ndarray, dirs: np.ndarray, degree: int,
                clamp: bool = True) -> np.ndarray:
    """Colour (N, 3) = max(sum_k basis_k(dir) sh_k + 0.5, 0), using the bands 0..degree only."""
    k = (degree + 1) ** 2
    sh = np.concatenate([sh_dc[:, None, :], sh_rest[:, : k - 1, :]], axis=1)  # (N, k, 3)
    basis = sh_basis(dirs, degree)                                               # (N, k)
    c = np.sum(basis[:, :, None] * sh, axis=1) + 0.5
    return np.maximum(c, 0) if clamp else c


# ---------------------------------------------------------------------------------------------- per Gaussian
def preprocess(params: dict, camera, sh_degree: int | None = None, dtype=np.float64, antialiased: bool = False) -> dict:
    """Screen-space quantities of every Gaussian (culled ones included, with ``culled`` True; their values are junk)."""
    dt = np.dtype(dtype)
    p = as_params(params, dt)
    n = p["means"].shape[0]
    stored = sh_degree_from_count(p["sh_rest"].shape[1] + 1)
    deg = stored if sh_degree is None else int(sh_degree)
    if not 0 <= deg <= stored:
        raise ValueError(f"sh_degree {sh_degree} must be in 0..{stored} (the stored degree)")

    W = np.asarray(camera.world_to_camera, dtype=np.float64)
    Wr, Wt = W[:3, :3].astype(dt), W[:3, 3].astype(dt)
    fx, fy, cx, cy = (dt.type(camera.fx), dt.type(camera.fy), dt.type(camera.cx), dt.type(camera.cy))
    width, height = int(camera.width), int(camera.height)
    cam_centre = (-W[:3, :3].T @ W[:3, 3]).astype(dt)

    t = p["means"] @ Wr.T + Wt  # (N, 3) camera space
    tx, ty, tz = t[:, 0], t[:, 1], t[:, 2]
    in_front = tz > dt.type(NEAR_PLANE)

    Sigma = covariance_3d(p["scales"], p["rotations"]) if n else np.zeros((0, 3, 3), dt)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        u, v = tx / tz, ty / tz
        lo_x, hi_x = (dt.type(-GUARD_BAND) * width - cx) / fx, (dt.type(1 + GUARD_BAND) * width - cx) / fx
        lo_y, hi_y = (dt.type(-GUARD_BAND) * height - cy) / fy, (dt.type(1 + GUARD_BAND) * height - cy) / fy
        uc, vc = np.minimum(np.maximum(u, lo_x), hi_x), np.minimum(np.maximum(v, lo_y), hi_y)
        J = np.zeros((n, 2, 3), dt)
        J[:, 0, 0] = fx / tz
        J[:, 0, 2] = -fx * uc / tz
        J[:, 1, 1] = fy / tz
        J[:, 1, 2] = -fy * vc / tz
        JW = J @ Wr
        cov2d = JW @ Sigma @ np.swapaxes(JW, -1, -2)
        det_undilated = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
        cov2d[:, 0, 0] += dt.type(DILATION)
        cov2d[:, 1, 1] += dt.type(DILATION)
        a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
        det = a * c - b * b
        conic = np.stack([c / det, -b / det, a / det], axis=-1)
        means2d = np.stack([fx * tx / tz + cx, fy * ty / tz + cy], axis=-1)
    culled = ~(in_front & (det > 0))

    dirs = p["means"] - cam_centre
    with np.errstate(divide="ignore", invalid="ignore"):
        dirs = dirs / np.sqrt(np.sum(dirs * dirs, axis=-1))[:, None]
    raw_colors = sh_to_color(p["sh_dc"], p["sh_rest"], dirs, deg, clamp=False)
    opacities = sigmoid(p["opacities"])
    if antialiased:
        with np.errstate(divide="ignore", invalid="ignore"):
            opacities = opacities * np.sqrt(np.maximum(np.nan_to_num(det_undilated / det), 0))
    return {
        "n": n,
        "sh_degree": deg,
        "t_cam": t,
        "depths": tz,
        "culled": culled,
        "near_margin": tz - dt.type(NEAR_PLANE),
        "guard_clamped": np.stack([u != uc, v != vc], axis=-1),
        "cov3d": Sigma,
        "cov2d": cov2d,
        "det": det,
        "conics": conic,
        "means2d": means2d,
        "opacities": opacities,
        "colors": np.maximum(raw_colors, 0),
        "color_clamped": raw_colors < 0,
        "dirs": dirs,
    }


# ---------------------------------------------------------------------------------------------- per pixel
def depth_order(pre: dict) -> np.ndarray:
    """Indices of the non-culled Gaussians sorted by depth, STABLE: equal depths keep index order."""
    idx = np.nonzero(~pre["culled"])[0]
    return idx[np.argsort(pre["depths"][idx], kind="stable")]


def composite_batch(pres: list, camera, background=(0.0, 0.0, 0.0), dtype=np.float64, record: bool = False,
                    margins: bool = True) -> dict:
    """Front-to-back alpha blending of B independent scenes (same camera and Gaussian count), every pixel against
    every non-culled Gaussian of its scene. Vectorized over (scene, pixel); step k handles the k-th nearest Gaussian of
    each scene. Scenes with fewer non-culled Gaussians are padded with a dummy of opacity 0, which the alpha < 1/255
    rule always skips. Outputs have a leading batch axis B. ``margins=False`` skips the pixel_margin bookkeeping
    (left at inf), which changes nothing else."""
    dt = np.dtype(dtype)
    width, height = int(camera.width), int(camera.height)
    bg = np.asarray(background, dtype=dt).reshape(3)
    B, n, P = len(pres), pres[0]["n"], width * height
    jj, ii = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")  # row j, column i
    px = (ii.reshape(-1) + 0.5).astype(dt)[None, :]
    py = (jj.reshape(-1) + 0.5).astype(dt)[None, :]

    # per scene: its Gaussians plus one dummy (index n: opacity 0, everything else 0)
    def stacked(key, shape):
        return np.stack([np.concatenate([pre[key], np.zeros((1,) + shape, dt)]) for pre in pres])

    means2d, conics, colors = stacked("means2d", (2,)), stacked("conics", (3,)), stacked("colors", (3,))
    opac, depths = stacked("opacities", ()), stacked("depths", ())
    orders = [depth_order(pre) for pre in pres]
    L = max([len(o) for o in orders] + [0])
    order = np.full((B, L), n, np.int64)
    for b, o in enumerate(orders):
        order[b, : len(o)] = o
    rows = np.arange(B)

    T = np.ones((B, P), dt)
    C = np.zeros((B, P, 3), dt)
    D = np.zeros((B, P), dt)
    n_contrib = np.zeros((B, P), np.int64)
    last_contrib = np.full((B, P), -1, np.int64)  # original index of the last contributing Gaussian (-1: none)
    done = np.zeros((B, P), bool)
    margin = np.full((B, P), np.inf)  # smallest |log(x / threshold)| over the decisions each pixel took
    visible = np.zeros((B, n + 1), bool)
    contrib_mask = np.zeros((B, n + 1, P), bool) if record else None
    clamp_mask = np.zeros((B, n + 1, P), bool) if record else None
    a_max, a_min, t_min = dt.type(ALPHA_MAX), dt.type(ALPHA_MIN), dt.type(T_MIN)

    for k in range(L):
        g = order[:, k]  # (B,) the k-th nearest Gaussian of each scene
        ca, cb, cc = (conics[rows, g, m][:, None] for m in range(3))
        o = opac[rows, g][:, None]
        dx = means2d[rows, g, 0][:, None] - px
        dy = means2d[rows, g, 1][:, None] - py
        power = dt.type(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        with np.errstate(under="ignore"):
            raw = o * np.exp(power)
        alpha = np.minimum(a_max, raw)
        evaluated = ~done & ~(power > 0)
        passes = evaluated & (alpha >= a_min)
        test_T = T * (dt.type(1) - alpha)
        stop = passes & (test_T < t_min)
        contrib = passes & ~stop
        if margins:
            with np.errstate(divide="ignore"):
                m_alpha = np.abs(np.log(raw.astype(np.float64) / ALPHA_MIN))
                m_term = np.abs(np.log(test_T.astype(np.float64) / T_MIN))
            margin = np.where(evaluated, np.minimum(margin, m_alpha), margin)
            margin = np.where(passes, np.minimum(margin, m_term), margin)

        w = alpha * T
        C = np.where(contrib[..., None], C + colors[rows, g][:, None, :] * w[..., None], C)
        D = np.where(contrib, D + depths[rows, g][:, None] * w, D)
        T = np.where(contrib, test_T, T)
        n_contrib += contrib
        last_contrib = np.where(contrib, g[:, None], last_contrib)
        done |= stop
        visible[rows, g] |= contrib.any(axis=1)
        if record:
            contrib_mask[rows, g] = contrib
            clamp_mask[rows, g] = contrib & (raw >= a_max)

    acc = dt.type(1) - T
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(acc > 0, D / acc, dt.type(0))
    out = {
        "rgb": (C + T[..., None] * bg).reshape(B, height, width, 3),
        "alpha": acc.reshape(B, height, width),
        "depth": depth.reshape(B, height, width),
        "final_T": T.reshape(B, height, width),
        "n_contrib": n_contrib.reshape(B, height, width),
        "last_contrib": last_contrib.reshape(B, height, width),
        "pixel_margin": margin.reshape(B, height, width),
        "visible": visible[:, :n],
        "order": orders,
    }
    if record:
        out["contrib_mask"] = contrib_mask[:, :n]
        out["alpha_clamp_mask"] = clamp_mask[:, :n]
    return out


def composite(pre: dict, camera, background=(0.0, 0.0, 0.0), dtype=np.float64, record: bool = False) -> dict:
    """Front-to-back alpha blending of one scene (``composite_batch`` with B = 1)."""
    out = composite_batch([pre], camera, background=background, dtype=dtype, record=record)
    return {k: v[0] for k, v in out.items()}


def depth_gaps(pre: dict) -> np.ndarray:
    """Per Gaussian, the smallest relative depth gap |d_g - d_h| / d_g to another non-culled Gaussian (inf if alone,
    0 for exact ties). Near-ties (> 0 but ~1e-7) may sort differently in a float32 implementation."""
    order = depth_order(pre)
    gaps = np.full(pre["n"], np.inf)
    if len(order) > 1:
        d = pre["depths"][order].astype(np.float64)
        diff = np.diff(d)
        near = np.minimum(np.concatenate([[np.inf], diff]), np.concatenate([diff, [np.inf]]))
        gaps[order] = near / np.abs(d)
    return gaps


def render_reference(params: dict, camera, background=(0.0, 0.0, 0.0), sh_degree: int | None = None,
                     dtype=np.float64, record: bool = False, antialiased: bool = False) -> dict:
    """Render with the reference model. Returns a dict:

    rgb (H, W, 3), alpha (H, W) = 1 - T, depth (H, W) expected depth (0 where alpha == 0), final_T (H, W),
    n_contrib (H, W) number of contributing Gaussians per pixel, last_contrib (H, W) index of the last one (-1: none),
    pixel_margin (H, W) min |log(x / threshold)| over the pixel's discrete decisions (alpha vs 1/255, T vs 1e-4):
      pixels with a small margin may legitimately flip between float32 and float64 implementations,
    means2d (N, 2), visible (N,) bool (contributes to at least one pixel), culled (N,) bool (near plane or det <= 0),
    depths (N,), near_margin (N,) = t_z - 0.2, conics (N, 3) (a, b, c), cov2d (N, 2, 2), opacities (N,),
    colors (N, 3) clamped, color_clamped (N, 3), guard_clamped (N, 2), order (sorted non-culled indices),
    depth_gap (N,) smallest relative depth gap to another Gaussian (0: exact tie; tiny: a float32 sort may differ).
    With record=True also contrib_mask (N, H*W) and alpha_clamp_mask (N, H*W) (alpha hit the 0.99 clamp).
    All floating arrays have ``dtype`` (float64 by default; float32 mimics a float32 implementation).
    """
    pre = preprocess(params, camera, sh_degree=sh_degree, dtype=dtype, antialiased=antialiased)
    out = composite(pre, camera, background=background, dtype=dtype, record=record)
    for k in ("means2d", "culled", "depths", "near_margin", "conics", "cov2d", "opacities", "colors",
              "color_clamped", "guard_clamped"):
        out[k] = pre[k]
    out["depth_gap"] = depth_gaps(pre)
    out["sh_degree"] = pre["sh_degree"]
    return out


# ---------------------------------------------------------------------------------------------- gradients
def weighted_loss(out: dict, weights: dict) -> float:
    """sum(w_rgb * rgb) + sum(w_alpha * alpha) + sum(w_depth * depth); a missing weight counts as zero."""
    total = 0.0
    for k in OUTPUT_NAMES:
        w = weights.get(k)
        if w is not None:
            total += float(np.sum(np.asarray(w, np.float64) * out[k].astype(np.float64)))
    return total


def _signature(out: dict, b: int, pre: dict) -> tuple:
    """Every discrete decision of scene b of a batch (to spot finite differences straddling a discontinuity/kink)."""
    return (pre["culled"].tobytes(), out["order"][b].tobytes(), out["contrib_mask"][b].tobytes(),
            out["alpha_clamp_mask"][b].tobytes(), pre["color_clamped"].tobytes(), pre["guard_clamped"].tobytes())


def render_losses(param_list: list, camera, weights: dict, background=(0.0, 0.0, 0.0), sh_degree: int | None = None,
                  record: bool = False, batch: int = 16, antialiased: bool = False):
    """``weighted_loss`` of each parameter set (float64), rendered in batches; with record, also their signatures."""
    losses, sigs = [], []
    for s0 in range(0, len(param_list), batch):
        pres = [preprocess(p, camera, sh_degree=sh_degree, dtype=np.float64, antialiased=antialiased)
                for p in param_list[s0: s0 + batch]]
        out = composite_batch(pres, camera, background=background, dtype=np.float64, record=record, margins=False)
        for b, pre in enumerate(pres):
            losses.append(weighted_loss({k: out[k][b] for k in OUTPUT_NAMES}, weights))
            if record:
                sigs.append(_signature(out, b, pre))
    return losses, sigs


def fd_gradients(params: dict, camera, weights: dict, background=(0.0, 0.0, 0.0), sh_degree: int | None = None,
                 eps: float = 1e-6, names=None, index_subset=None, return_unreliable: bool = False,
                 antialiased: bool = False):
    """Central finite differences (float64) of ``weighted_loss`` w.r.t. every raw parameter entry.

    ``names``: parameter names to differentiate (default: all of PARAM_NAMES). ``index_subset``: Gaussian indices to
    differentiate (default: all); entries of other Gaussians are NaN in the result (never silently zero).
    Returns {name: array shaped like params[name]}. With ``return_unreliable=True`` also returns
    {name: bool array}: True where the +eps and -eps renders took different discrete decisions (culling, sort order,
    contributing set, 0.99 clamp, colour clamp, guard-band clamp), i.e. the difference straddles a kink or jump.

    Rounding noise: the loss is a sum over pixels, so its float64 rounding (~1e-16 |loss|) is divided by 2 eps; the
    depth output D / (1 - T) is noisier still where alpha is small (~1e-16 depth / alpha per pixel). With depth
    weights, eps = 1e-5 .. 1e-4 gives cleaner differences for smooth scenes.
    """
    base = as_params(params, np.float64)
    n = base["means"].shape[0]
    names = PARAM_NAMES if names is None else tuple(names)
    subset = np.arange(n) if index_subset is None else np.asarray(index_subset, dtype=np.int64).reshape(-1)
    for name in names:
        if name not in PARAM_NAMES:
            raise ValueError(f"unknown parameter {name!r}")

    keys, plist = [], []
    for name in names:
        for i in subset:
            for sub in np.ndindex(base[name].shape[1:]):
                key = (int(i),) + sub
                for sign in (1.0, -1.0):
                    q = {k: v.copy() for k, v in base.items()}
                    q[name][key] += sign * eps
                    plist.append(q)
                keys.append((name, key))
    losses, sigs = render_losses(plist, camera, weights, background=background, sh_degree=sh_degree,
                                 record=return_unreliable, antialiased=antialiased)

    grads = {name: np.full(base[name].shape, np.nan) for name in names}
    unreliable = {name: np.zeros(base[name].shape, bool) for name in names}
    for m, (name, key) in enumerate(keys):
        grads[name][key] = (losses[2 * m] - losses[2 * m + 1]) / (2 * eps)
        if return_unreliable:
            unreliable[name][key] = sigs[2 * m] != sigs[2 * m + 1]
    return (grads, unreliable) if return_unreliable else grads
