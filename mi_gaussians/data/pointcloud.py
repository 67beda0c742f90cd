"""Initial point clouds for layouts without SfM points, and the scene extent of a set of cameras.

Reference behaviour (3DGS ``readNerfSyntheticInfo``): 100k points uniform in the cube ``[-1.3, 1.3]^3``. The reference
gives them the colours ``SH2RGB(U[0,1)/255)``, i.e. a grey of about 0.5; ``docs/conventions.md`` asks for random
colours, so ours are uniform in ``[0, 1)^3`` (the optimizer rewrites them within a few hundred steps either way).

For instant-ngp captures (no points, arbitrary world frame) the cube is centred on the *focus point* of the cameras,
the point nearest all optical axes in the least-squares sense, with a half-size equal to the median distance from the
camera centres to that point: the cube then reaches back to the cameras and holds everything they look at.

``random_init = "frustum"`` (:func:`points_in_view`) samples where the training cameras look instead of a fixed cube:
candidates along each camera's pixel rays, uniform in depth between the near plane and the far side of the camera
rig (or twice the distance to the point the cameras look at), kept with probability proportional to the square of the number of training cameras that see them -- the
region the cameras share, whatever the scene's size (a room seen from inside as well as an object seen from around it).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .. import config

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


#: Points sampled (evenly strided) by :func:`seen_depth`: the median of this many is as good as of all.
SEEN_DEPTH_POINTS = 20_000


def seen_depth(cameras, points: np.ndarray, max_points: int = SEEN_DEPTH_POINTS) -> float | None:
    """How far away the cameras see the scene: per camera, the median view-space depth of the ``points`` it sees (in
    front of it, inside its image), then the median over the cameras that see any; ``None`` when none does.

    ``points``: (N, 3) world positions (the run's initial points); at most ``max_points`` of them, evenly strided
    (``max_points <= 0``: all of them)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) > max_points > 0:
        p = p[np.linspace(0, len(p) - 1, max_points).astype(np.int64)]
    depths = []
    for c in cameras:
        uv, z = c.project(p)
        seen = c.sees(uv, z)
        if seen.any():
            depths.append(float(np.median(z[seen])))
    return float(np.median(depths)) if depths else None


def scene_extent(cameras, points: np.ndarray | None, rule: str = config.DataConfig.extent) -> float:
    """The scene's length scale for training (``extent``): the position learning rate, the clone/split boundary and
    the large-Gaussian prune are fractions of it (``data.extent``, :data:`mi_gaussians.config.EXTENTS`).

    'cameras': :func:`camera_extent` of the camera centres (the reference's ``getNerfppNorm``, gsplat's
    ``scene_scale``). 'depth' (the default): :func:`seen_depth` of ``points``, which does not depend on the rig's
    shape (an orbit's spread, a hemisphere's and a ring's differ at the same distance) and makes a length rule one
    angle in every view (a Gaussian of 1 % of it covers about a hundredth of a radian at the depth seen). A
    forward-facing rig (a room, an LLFF capture) stands close together and looks far, and its spread alone makes
    every length rule a fraction of the wrong size (mi_room: 0.52 by its cameras, 3.10 by the depth they see; a
    Gaussian over 5 cm, a tenth of 0.52, was pruned from walls seen 3 m away); around an object the spread is the
    larger (mi_objects: 4.87 against 4.01). 'scene': the larger of the two. 'depth' and 'scene' fall back to the
    spread when no camera sees a point (:func:`scene_scale` says so). ValueError when the result is 0 or not finite
    (:class:`DegenerateScale`): every length rule would be 0 and the Gaussians would never move."""
    return scene_scale(cameras, points, rule)[0]


class DegenerateScale(ValueError):
    """A scene with no length scale (0 or not finite): nothing a run could train with."""


def scene_scale(cameras, points: np.ndarray | None, rule: str = config.DataConfig.extent) -> tuple[float, str | None]:
    """(:func:`scene_extent`, None), or (the cameras' spread, why) when ``rule`` fell back to it: no camera sees a
    point. Raises :class:`DegenerateScale` naming why when the scale is 0 or not finite."""
    cams = list(cameras)
    spread = camera_extent(np.stack([c.center for c in cams]))[1]
    if rule not in config.EXTENTS:
        raise ValueError(f"scene_extent: unknown rule {rule!r} (expected one of {', '.join(config.EXTENTS)})")
    depth = None if rule == "cameras" or points is None else seen_depth(cams, points)
    fallback = None
    if rule == "cameras":
        value = spread
    elif depth is None:
        value = spread
        n = 0 if points is None else len(points)
        fallback = (f"none of the {n:,} initial points lies in front of a training camera and inside its image, so "
                    f"the length scale (data.extent={rule}) falls back to the cameras' spread, {spread:.6g}")
    else:
        value = depth if rule == "depth" else max(spread, depth)
    if not (np.isfinite(value) and value > 0):
        cams_said = f"{len(cams)} training camera{'s' if len(cams) != 1 else ''}"
        where = ("so no spread" if len(cams) == 1 else "all at one point (spread 0)" if spread == 0 else
                 f"spread {spread}")
        seen = "" if rule == "cameras" else (f", and {fallback.partition(', so')[0]}" if fallback else "")
        advice = ("measure it by the depth the cameras see the points at (--set data.extent=depth), or train on more "
                  "views (--test-every)" if rule == "cameras" else
                  "give initial points the cameras see (e.g. --init frustum), or more training views (--test-every)")
        raise DegenerateScale(f"the scene has no length scale (data.extent={rule} gives {value:g}): {cams_said}, "
                              f"{where}{seen}; every position rate and size rule would be 0 and the Gaussians would "
                              f"never move: {advice}")
    return float(value), fallback


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



#: Initial point samplers of layouts without SfM points (``DataConfig.random_init``, named in ``config``): the
#: reference's cube (Blender: [-1.3, 1.3]^3; others: around the focus point) or the cameras' frustums
#: (:func:`points_in_view`).
RANDOM_INITS = config.RANDOM_INITS
#: Near plane of the frustum sampler (the rasterizer's default near plane).
FRUSTUM_NEAR = 0.2


def points_in_view(n: int, cameras, seed: int, near: float = FRUSTUM_NEAR,
                   oversample: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random points where the cameras look, with uniform random colours (see the module docstring).

    ``oversample * n`` candidates: a camera drawn uniformly, a pixel position uniform in its image, a depth z
    uniform in [near, far] (uniform per ray: denser near the camera than uniform in volume, which on our rigs puts
    more points inside the scene: measured on mi_objects and mi_room), far = the larger of the camera's
    distance to the rig's centre plus the rig's extent (:func:`camera_extent`) and twice its distance to the
    :func:`focus_point` (forward-facing rigs, whose extent is small); ``n`` of them are drawn without replacement
    with probability proportional to the square of the number of cameras that see them (in front of their near
    plane, inside their image). Returns (xyz (n, 3) float32, rgb (n, 3) float32)."""
    cams = list(cameras)
    if n < 0 or not cams:
        raise ValueError(f"points_in_view: need n >= 0 and at least one camera (n={n}, {len(cams)} cameras)")
    rng = np.random.default_rng(seed)
    centers = np.stack([c.center for c in cams])
    mean, extent = camera_extent(centers)
    focus = focus_point(centers, np.stack([c.world_to_camera[2, :3] for c in cams]))
    far = np.maximum.reduce([np.linalg.norm(centers - mean, axis=1) + extent,
                             2.0 * np.linalg.norm(centers - focus, axis=1), np.full(len(cams), 2.0 * near)])
    m = max(int(oversample), 1) * n
    which = rng.integers(len(cams), size=m)
    xyz = np.zeros((m, 3))
    u3 = rng.random((m, 3))
    for i, c in enumerate(cams):
        sel = np.flatnonzero(which == i)
        if not len(sel):
            continue
        u, v, r = u3[sel, 0] * c.width, u3[sel, 1] * c.height, u3[sel, 2]
        z = near + r * (far[i] - near)
        p_cam = np.stack([(u - c.cx) / c.fx * z, (v - c.cy) / c.fy * z, z], axis=1)
        R, t = c.world_to_camera[:3, :3], c.world_to_camera[:3, 3]
        xyz[sel] = (p_cam - t) @ R                       # R^T (p - t) per row
    seen = np.zeros(m)
    for c in cams:
        uv, z = c.project(xyz)
        with np.errstate(invalid="ignore"):
            seen += (z > near) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
    weight = np.maximum(seen, 1.0) ** 2                  # (each candidate is in its own camera's frustum)
    keep = rng.choice(m, size=n, replace=False, p=weight / weight.sum()) if n else np.zeros(0, np.int64)
    rgb = rng.random((n, 3))
    return xyz[keep].astype(np.float32), rgb.astype(np.float32)
