"""Initial point clouds for layouts without SfM points, and the scene extent of a set of cameras.

Reference behaviour (3DGS ``readNerfSyntheticInfo``): 100k points uniform in the cube ``[-1.3, 1.3]^3``. The reference
gives them the colours ``SH2RGB(U[0,1)/255)``, i.e. a grey of about 0.5; ``conventions.md`` asks for random colours, so
ours are uniform in ``[0, 1)^3`` (the optimizer rewrites them within a few hundred steps either way).

For instant-ngp captures (no points, arbitrary world frame) the cube is centred on the *focus point* of the cameras,
the point nearest all optical axes in the least-squares sense, with a half-size equal to the median distance from the
camera centres to that point: the cube then reaches back to the cameras and holds everything they look at.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

# The reference's cube for NeRF-synthetic scenes: [-1.3, 1.3]^3.
BLENDER_BOX_HALF_SIZE = 1.3


def camera_extent(centers: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and extent of a set of camera centres, as 3DGS ``getNerfppNorm`` computes them.

    centers: (N, 3) camera centres.  Returns (mean (3,) float64, extent = 1.1 * max distance to the mean).
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    if len(c) == 0:
        raise ValueError("camera_extent: no camera centres")
    mean = c.mean(axis=0)
    return mean, 1.1 * float(np.linalg.norm(c - mean, axis=1).max())


def random_points_in_box(n: int, lo: Sequence[float], hi: Sequence[float], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform in the axis-aligned box ``[lo, hi]`` with uniform random colours.

    Returns (xyz (n, 3) float32, rgb (n, 3) float32 in [0, 1)); the same seed gives the same points.
    """
    if n < 0:
        raise ValueError(f"random_points_in_box: the number of points must be >= 0, got {n}")
    lo_a, hi_a = np.asarray(lo, dtype=np.float64).reshape(3), np.asarray(hi, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(lo_a)) and np.all(np.isfinite(hi_a)) and np.all(hi_a >= lo_a)):
        raise ValueError(f"random_points_in_box: invalid box {lo_a.tolist()} .. {hi_a.tolist()}")
    rng = np.random.default_rng(seed)
    xyz = lo_a + rng.random((n, 3)) * (hi_a - lo_a)
    rgb = rng.random((n, 3))
    return xyz.astype(np.float32), rgb.astype(np.float32)


def focus_point(centers: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The point nearest all the lines ``centers[i] + t * directions[i]`` (least squares), (3,) float64.

    centers, directions: (N, 3).  When the lines are (nearly) parallel, e.g. a forward-facing capture, the system is
    ill-conditioned; a weak pull towards the point one mean camera spread in front of the mean centre keeps it defined.
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    # sum_i (I - d_i d_i^T) (p - c_i) = 0
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    a = proj.sum(axis=0)
    b = np.einsum("nij,nj->i", proj, c)
    mean_c = c.mean(axis=0)
    spread = float(np.linalg.norm(c - mean_c, axis=1).mean()) or 1.0
    prior = mean_c + spread * d.mean(axis=0)
    eps = 1e-6 * len(c)
    return np.linalg.solve(a + eps * np.eye(3), b + eps * prior)


def points_around_cameras(n: int, centers: np.ndarray, directions: np.ndarray,
                          seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random points in a cube centred on :func:`focus_point` with half-size the median camera distance to it.

    centers, directions: (N, 3) camera centres and forward (optical-axis) directions.
    Returns (xyz (n, 3) float32, rgb (n, 3) float32).
    """
    p = focus_point(centers, directions)
    half = float(np.median(np.linalg.norm(np.asarray(centers, dtype=np.float64).reshape(-1, 3) - p, axis=1)))
    if not np.isfinite(half) or half <= 0.0:
        half = 1.0
    return random_points_in_box(n, p - half, p + half, seed)


def blender_random_points(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The reference's initial points for NeRF-synthetic scenes: ``n`` points uniform in ``[-1.3, 1.3]^3``."""
    h = BLENDER_BOX_HALF_SIZE
    return random_points_in_box(n, (-h, -h, -h), (h, h, h), seed)

