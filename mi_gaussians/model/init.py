"""Initialization of Gaussians from a point cloud (COLMAP points3D, a dataset's random points), reference rules:

* colour -> SH DC ``(rgb - 0.5) / SH_C0``, higher SH bands zero;
* scale = ``log(sqrt(d2))`` on all three axes, where ``d2`` is the mean squared distance to the 3 nearest other points,
  floored at 1e-7 (reference: ``clamp_min(distCUDA2(points), 1e-7)``);
* identity rotation ``(1, 0, 0, 0)``; opacity ``logit(0.1)``.

Differences from the reference, documented: the reference's simple-knn ``distCUDA2`` is an approximate (box-based)
search in float32; we use an exact k-d tree search in float64. Duplicated points count as neighbours at distance 0,
exactly as in the reference, so a point with 3 or more duplicates gets the floor ``log(sqrt(1e-7))``. With fewer than
4 points the mean is over the ``N - 1`` available neighbours (the reference would average in FLT_MAX for missing
neighbours); a single point has no neighbour and gets the floor.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..conventions import logit, rgb_to_sh_dc, sh_coeff_count

#: Floor on the mean squared neighbour distance (reference value).
MIN_DIST2 = 1e-7
#: Number of nearest neighbours averaged for the initial scale.
KNN = 3


def mean_knn_dist2(xyz, k: int = KNN) -> np.ndarray:
    """Mean squared distance of each point to its ``k`` nearest other points, float64 (N,), NOT floored.

    ``xyz`` (N, 3). With ``N - 1 < k`` the mean is over the ``N - 1`` others; ``N == 1`` gives 0."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = xyz.shape[0]
    kk = min(k, n - 1)
    if kk <= 0:
        return np.zeros(n, np.float64)
    tree = cKDTree(xyz)
    # k + 1 because the query point itself is returned (distance 0). With duplicates the first zero distance may be a
    # duplicate instead of the point itself: both are 0, so dropping the first column is the same either way.
    dist, _ = tree.query(xyz, k=kk + 1)
    d = dist[:, 1:]
    return np.mean(d * d, axis=1)


def init_scales(xyz, k: int = KNN, min_dist2: float = MIN_DIST2, factor: float = 1.0) -> np.ndarray:
    """Isotropic log-scales (N, 3) float32: ``log(factor * sqrt(max(mean_knn_dist2, min_dist2)))`` on each axis."""
    d2 = np.maximum(mean_knn_dist2(xyz, k), min_dist2)
    s = 0.5 * np.log(d2) + (np.log(factor) if factor != 1.0 else 0.0)
    return np.repeat(s[:, None], 3, axis=1).astype(np.float32)


def init_from_points(xyz, rgb, sh_degree: int = 3, initial_opacity: float = 0.1,
                     scale_factor: float = 1.0) -> dict[str, np.ndarray]:
    """Raw Gaussian parameters initialized from points, keyed like ``Gaussians.from_numpy`` (all float32).

    ``xyz`` (N, 3) positions, ``rgb`` (N, 3) colours in [0, 1] (floats) or 0..255 (uint8 arrays, divided by 255),
    ``sh_degree`` 0..3 (sets the shape of ``sh_rest``: (N, (d + 1)^2 - 1, 3) zeros), ``initial_opacity`` in (0, 1),
    ``scale_factor`` > 0 multiplies the scales (gsplat's ``init_scale``, 0.1 in its MCMC recipe).
    Returns means (N, 3), scales (N, 3), rotations (N, 4) = (1, 0, 0, 0), opacities (N,) = logit(initial_opacity),
    sh_dc (N, 3), sh_rest. Raises ValueError for empty input, mismatched shapes or non-finite values."""
    if not isinstance(sh_degree, (int, np.integer)) or not 0 <= int(sh_degree) <= 3:
        raise ValueError(f"sh_degree must be an integer in 0..3, got {sh_degree!r}")
    if not 0.0 < float(initial_opacity) < 1.0:
        raise ValueError(f"initial_opacity must be strictly between 0 and 1, got {initial_opacity!r}")
    if not float(scale_factor) > 0.0 or not np.isfinite(float(scale_factor)):
        raise ValueError(f"scale_factor must be a positive number, got {scale_factor!r}")
    xyz = np.asarray(xyz)
    rgb = np.asarray(rgb)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {xyz.shape}")
    n = xyz.shape[0]
    if n == 0:
        raise ValueError("cannot initialize Gaussians from an empty point cloud")
    if rgb.shape != (n, 3):
        raise ValueError(f"colours must have shape ({n}, 3) to match the points, got {rgb.shape}")
    if rgb.dtype == np.uint8:
        rgb = rgb.astype(np.float64) / 255.0
    xyz = xyz.astype(np.float64)
    rgb = rgb.astype(np.float64)
    for name, a in (("points", xyz), ("colours", rgb)):
        bad = int((~np.isfinite(a)).sum())
        if bad:
            raise ValueError(f"{bad} non-finite value(s) in the {name}")

    k_rest = sh_coeff_count(sh_degree) - 1
    return {
        "means": xyz.astype(np.float32),
        "scales": init_scales(xyz, factor=float(scale_factor)),
        "rotations": np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1)),
        "opacities": np.full(n, logit(np.float64(initial_opacity)), dtype=np.float32),
        "sh_dc": rgb_to_sh_dc(rgb).astype(np.float32),
        "sh_rest": np.zeros((n, k_rest, 3), np.float32),
    }

