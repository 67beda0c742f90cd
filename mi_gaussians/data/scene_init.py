"""Initial points for a Mitsuba scene dataset (``mi_gaussians.data.scene_dataset``).

Four methods (``SceneConfig.init``):

- ``shapes`` (default): points sampled on the scene's shapes with Mitsuba's own ``Shape.sample_position``
  (uniform by area over all shapes), each coloured by the mean of the training references at the pixels where it is
  visible (projected into every training camera, occlusion tested with ``Scene.ray_test``); points no training camera
  sees are dropped. Exact geometry and colours: it needs no structure from motion and wins on quality and time
  (README, "Mitsuba scenes").
- ``random``: uniform in the scene's bounding box with random colours (the reference's synthetic-scene init).
- ``triangulate``: SIFT points of the training references triangulated with pycolmap from the scene's exact cameras
  (:mod:`mi_gaussians.data.triangulate`, as for a Blender dataset: COLMAP's ``point_triangulator`` on known poses):
  the points a COLMAP capture starts from, without structure from motion's chance of placing cameras wrongly.
- ``sfm``: structure from motion with pycolmap on the (sRGB-encoded) training references, as for photographs, then
  aligned to the known cameras by the similarity that maps the SfM camera centres onto the true ones (Umeyama over
  the cameras that agree). On renders of a synthetic scene, structure from motion often registers cameras wrongly
  (mirrored, or in a second cluster): a reconstruction where fewer than half agree is refused.

The ``triangulate`` and ``sfm`` points are cached next to the references (``work``).

Colours are in the training colour space: sRGB-encoded, or linear radiance with ``linear=True``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable

import numpy as np

from ..config import SCENE_INITS, TriangulateConfig
from ..imwrite import linear_to_srgb, srgb_to_linear, write_png
from ..io_utils import atomic_path
from . import pointcloud as _pc
from .camera import camera_center
from .triangulate import NoPoints, cache_key, load_cached_points, triangulate

INIT_METHODS = SCENE_INITS      # (named in config)


def initial_points(scene, method: str, n: int, train_views, work: Path, seed: int = 0, linear: bool = False,
                   log: Callable[[str], None] | None = None,
                   triangulation: TriangulateConfig = TriangulateConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (M, 3) float32, rgb (M, 3) float32) by ``method`` (see the module docstring); ``work``: the work
    and cache folder of the ``triangulate`` and ``sfm`` methods (``triangulation``: the former's settings)."""
    if method not in INIT_METHODS:
        raise ValueError(f"unknown initialization {method!r} (expected one of {', '.join(INIT_METHODS)})")
    if method == "triangulate":
        # (a folder per settings and seed, as a dataset folder's: runs with other triangulation settings do not share)
        tri = triangulate(train_views, "linear" if linear else "srgb", work / cache_key(work.name, triangulation, seed),
                          triangulation, seed, where="the scene's references", log=log)
        if len(tri.xyz) < triangulation.min_points:
            raise NoPoints(f"the triangulation of the references kept {len(tri.xyz):,} points, fewer than "
                           f"triangulate.min_points ({triangulation.min_points}) (use --init shapes)")
        if log is not None and not tri.cached:
            log(f"initial points: {len(tri.xyz):,} triangulated from the references with the scene's cameras")
        return tri.xyz, tri.rgb
    if method != "sfm" and n < 1:
        raise ValueError(f"the number of initial points must be >= 1, got {n}")
    if method == "random":
        b = scene.bbox()
        return _pc.random_points_in_box(n, list(b.min), list(b.max), seed)
    if method == "shapes":
        xyz = sample_surface_points(scene, n, seed)
        rgb, seen = colour_from_views(scene, xyz, [v.camera for v in train_views],
                                      [v.load_image() for v in train_views])
        if log is not None:
            log(f"initial points: {int(seen.sum()):,} of {n:,} sampled on the shapes are seen by a training camera")
        if not seen.any():
            raise ValueError("no point sampled on the scene's shapes is visible from a training camera "
                             "(check the cameras, or use --init random)")
        return xyz[seen], rgb[seen]
    return sfm_points(train_views, work, linear=linear, log=log)


# ---------------------------------------------------------------------------------------------------- shapes
def sample_surface_points(scene, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points uniform by area on the scene's shapes (``Shape.sample_position``); Gaussians (``ellipsoids``
    shapes) and shapes that cannot be sampled are skipped. (n, 3) float32."""
    import mitsuba as mi

    shapes, areas = [], []
    for s in scene.shapes():
        if s.is_ellipsoids():
            continue
        try:
            a = float(np.array(s.surface_area()).ravel()[0])
        except Exception:       # e.g. shapes that do not implement surface_area
            continue
        if np.isfinite(a) and a > 0:
            shapes.append(s)
            areas.append(a)
    if not shapes:
        k = len(scene.shapes())
        raise ValueError(f"the scene has no shape that Mitsuba can sample positions on (its {k} shape"
                         f"{'s are' if k != 1 else ' is'} Gaussians or without a surface area), so the initial "
                         "points cannot be sampled on shapes (--init shapes): start from random points in its "
                         "bounding box (--init random) or from structure from motion on the references (--init sfm)")
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(n, np.asarray(areas) / np.sum(areas))
    out = []
    for s, k in zip(shapes, counts):
        if k == 0:
            continue
        u = rng.random((2, k)).astype(np.float32)
        ps = s.sample_position(0.0, mi.Point2f(u[0], u[1]))
        out.append(np.array(ps.p, dtype=np.float32).reshape(3, k).T)     # Dr.Jit gives (3, k)
    xyz = np.concatenate(out, axis=0)
    return xyz[np.all(np.isfinite(xyz), axis=1)]


def visible_from(scene, cam, xyz: np.ndarray, rel_eps: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """(visible (N,) bool, pixel (N, 2) int) of world points in one camera: inside the image, in front of it, and
    with nothing in between (a shadow ray from the camera centre stopping ``rel_eps`` short of the point)."""
    import drjit as dr
    import mitsuba as mi

    uv, z = cam.project(xyz)
    with np.errstate(invalid="ignore"):
        inside = (z > 0) & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) \
            & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    pix = np.zeros((len(xyz), 2), np.int64)
    pix[inside] = np.floor(uv[inside]).astype(np.int64)
    idx = np.flatnonzero(inside)
    if len(idx) == 0:
        return inside, pix
    o = cam.center
    d = xyz[idx].astype(np.float64) - o
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(len(idx), o[i], np.float32)) for i in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, i].astype(np.float32)) for i in range(3)]))
    ray.maxt = mi.Float((dist * (1.0 - rel_eps)).astype(np.float32))
    with dr.suspend_grad():
        occluded = np.array(scene.ray_test(ray), dtype=bool)
    vis = inside.copy()
    vis[idx] = ~occluded
    return vis, pix


def colour_from_views(scene, xyz: np.ndarray, cams, images) -> tuple[np.ndarray, np.ndarray]:
    """Mean image colour of each point over the cameras that see it: (rgb (N, 3) float32, seen (N,) bool)."""
    total = np.zeros((len(xyz), 3), np.float64)
    count = np.zeros(len(xyz), np.int64)
    for cam, img in zip(cams, images):
        vis, pix = visible_from(scene, cam, xyz)
        total[vis] += img[pix[vis, 1], pix[vis, 0], :3]
        count[vis] += 1
    seen = count > 0
    rgb = np.zeros((len(xyz), 3), np.float32)
    rgb[seen] = (total[seen] / count[seen, None]).astype(np.float32)
    return rgb, seen


# ---------------------------------------------------------------------------------------------------- SfM
def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimizing sum |s R src + t - dst|^2 (Umeyama 1991). src, dst: (N, 3), N >= 3."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


#: a camera agrees with an alignment when its centre lands within this fraction of the cameras' spread of the truth
ALIGN_TOLERANCE = 0.02


def robust_umeyama(src: np.ndarray, dst: np.ndarray, tolerance: float = ALIGN_TOLERANCE, tries: int = 500,
                   seed: int = 0) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """(s, R, t, inliers): :func:`umeyama` fitted to the pairs that agree with it (RANSAC over triples, then refitted
    on the largest consensus), an inlier landing within ``tolerance`` times the spread of ``dst`` (the largest
    distance from its mean). Structure from motion can register a few images of a symmetric scene mirrored or
    flipped; a least-squares fit over every camera is dragged off by them (measured: 7 of 64 cameras moved the whole
    point cloud by 70 % of the rig's size), the consensus is not."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    n = len(src)
    bound = tolerance * max(float(np.linalg.norm(dst - dst.mean(0), axis=1).max()), 1e-12)
    rng = np.random.default_rng(seed)
    s, R, t = umeyama(src, dst)
    best = np.linalg.norm(s * src @ R.T + t - dst, axis=1) <= bound
    for _ in range(tries if n > 3 else 0):
        idx = rng.choice(n, 3, replace=False)
        s, R, t = umeyama(src[idx], dst[idx])
        inliers = np.linalg.norm(s * src @ R.T + t - dst, axis=1) <= bound
        if inliers.sum() > best.sum():
            best = inliers
    if best.sum() >= 3:
        s, R, t = umeyama(src[best], dst[best])
        best = np.linalg.norm(s * src @ R.T + t - dst, axis=1) <= bound
    return s, R, t, best


def sfm_points(train_views, work: Path, linear: bool = False,
               log: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """SfM points of the training references, in the scene's frame (cached in ``work/points.npz``)."""
    from .colmap import read_model
    from .convert import convert

    cached = work / "points.npz"
    # (a cache without "aligned_on" was aligned by a least-squares fit over every camera, which a few misregistered
    # ones could drag off: computed again)
    z = load_cached_points(cached, ("aligned_on",), log or (lambda line: None))
    if z is not None:
        xyz, rgb, agreeing = z["xyz"], z["rgb"], int(z["aligned_on"])
    else:
        inp = work / "input"
        if inp.exists():
            shutil.rmtree(inp)
        inp.mkdir(parents=True)
        for v in train_views:
            img = v.load_image()
            write_png(inp / f"{v.name}.png", img if not linear else linear_to_srgb(np.maximum(img, 0)))
        convert(inp, work, camera_model="PINHOLE", overwrite=True, progress=log)
        model = read_model(work / "sparse" / "0")
        truth = {v.name: v.camera.center for v in train_views}
        pairs = [(c.name, camera_center(c.world_to_camera)) for c in model.images]
        pairs = [(truth[os.path.splitext(n)[0]], c) for n, c in pairs if os.path.splitext(n)[0] in truth]
        if len(pairs) < 3 or len(model.points_xyz) == 0:
            raise ValueError(f"{work}: structure from motion registered too few references ({len(pairs)}) to "
                             "align to the scene (use --init triangulate or --init shapes)")
        s, R, t, agree = robust_umeyama(np.array([c for _, c in pairs]), np.array([g for g, _ in pairs]))
        agreeing = int(agree.sum())
        if agreeing < max(3, len(pairs) // 2):
            raise ValueError(f"{work}: structure from motion's cameras do not fit the scene's: only {agreeing} of "
                             f"{len(pairs)} land within {ALIGN_TOLERANCE:.0%} of the rig's size of their true place "
                             "under one similarity (use --init triangulate, which keeps the scene's cameras, or "
                             "--init shapes)")
        xyz = (s * model.points_xyz.astype(np.float64) @ R.T + t).astype(np.float32)
        rgb = model.points_rgb.astype(np.float32)
        with atomic_path(cached, suffix=".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, xyz=xyz, rgb=rgb, aligned_on=np.int64(agreeing))
    if log is not None:
        log(f"initial points: {len(xyz):,} from structure from motion (aligned on the {agreeing} cameras that agree)")
    return xyz, (srgb_to_linear(rgb) if linear else rgb)
