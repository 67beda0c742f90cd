"""Initial points for posed images without points of their own (Blender, instant-ngp): triangulated from the known
poses with pycolmap, as COLMAP's ``point_triangulator`` does after structure from motion, without throwing the poses
away.

Stages (each logged with the seconds it took):

1. **images**: the training views as the dataset loads them (undistorted, at the training resolution) written as
   8-bit PNGs (sRGB-encoded), with a mask where the view has alpha (a Blender RGBA image, a COLMAP mask): features
   on the background are not matched.
2. **features**: SIFT (``pycolmap.extract_features``), one camera per image, with our intrinsics written into the
   database before matching, so that verification uses them (calibrated two-view geometry).
3. **matching**: the pairs of cameras whose views overlap, chosen from the poses (:func:`choose_pairs`: every pair
   up to ``exhaustive_below`` images, else each camera's ``neighbours`` nearest among those looking the same way),
   matched and verified geometrically (RANSAC, seeded).
4. **triangulation**: a ``pycolmap.Reconstruction`` of our cameras and poses (ids taken from the database), and
   ``pycolmap.triangulate_points`` with the poses held fixed (its bundle adjustment moves the points only);
   then the points with a reprojection error above ``max_reprojection_error`` px, a triangulation angle below
   ``min_angle`` degrees or a track shorter than ``min_track_length`` images are dropped. Colours: the mean of the
   track's pixels.

The result is cached in ``cache/<key>/points.npz``, ``key`` hashing the images (the dataset's fingerprint), the
resolution, the background and the settings: a second run reuses it. Cameras that all share one centre (no
baseline), fewer than two images, and images in which no point could be triangulated (too little texture) are
one-line :class:`NoPoints` errors; ``data.init=auto`` then falls back to the random cube, saying so.
"""

from __future__ import annotations

import contextlib

import hashlib
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..config import TriangulateConfig
from ..io_utils import atomic_path

CACHE_VERSION = 1        # bump when what the triangulation computes changes


class NoPoints(ValueError):
    """No points could be triangulated from these views (too few images, no baseline, too little texture, too few
    points kept): ``data.init=auto`` then starts from random points. Images that cannot be read are other errors."""


@dataclass
class Triangulated:
    """Points triangulated from a dataset's training views: ``xyz`` (N, 3), ``rgb`` (N, 3) float32 in the dataset's
    colour space, the seconds each stage took, the pairs matched and verified, and whether it came from the cache."""

    xyz: np.ndarray
    rgb: np.ndarray
    seconds: dict = field(default_factory=dict)
    pairs: int = 0
    verified_pairs: int = 0
    cached: bool = False


def choose_pairs(cameras, neighbours: int, exhaustive_below: int) -> list[tuple[int, int]]:
    """The pairs (i < j) of cameras to match: all of them for at most ``exhaustive_below`` cameras; else, for each
    camera, the ``neighbours`` nearest (camera centres) among those whose viewing directions are within 90 degrees
    of its own (the others cannot see the same side of anything), the union of both directions."""
    n = len(cameras)
    if n <= exhaustive_below:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    centres = np.stack([c.center for c in cameras])
    axes = np.stack([c.world_to_camera[2, :3] for c in cameras])          # each camera's +z in world space
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    facing = axes @ axes.T > 0.0
    pairs = set()
    for i in range(n):
        candidates = [j for j in np.argsort(dist[i], kind="stable") if j != i and facing[i, j]]
        for j in candidates[:neighbours]:
            pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def check_cameras(cameras, where: str) -> None:
    """At least two cameras, not all at one centre (there would be no baseline to triangulate from)."""
    if len(cameras) < 2:
        raise NoPoints(f"{where}: triangulating points needs at least two training images ({len(cameras)} here)")
    centres = np.stack([c.center for c in cameras])
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
    scale = max(float(np.linalg.norm(centres, axis=1).max()), 1.0)
    if spread <= 1e-6 * scale:
        raise NoPoints(f"{where}: every camera has the same centre (a panorama): there is no baseline to "
                         "triangulate points from")


def cache_key(fingerprint: str, cfg: TriangulateConfig, seed: int) -> str:
    text = json.dumps({"version": CACHE_VERSION, "dataset": fingerprint, "settings": asdict(cfg), "seed": seed},
                      sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def load_cached_points(cached: Path, extra: tuple[str, ...], say: Callable[[str], None]) -> dict | None:
    """The arrays of a points cache we wrote (``xyz``, ``rgb`` and ``extra``), or None when there is none. A damaged
    one (truncated, emptied, overwritten: not the user's fault) is removed with one line to ``say`` and None is
    returned, so that it is computed again instead of failing every later run."""
    import zipfile

    if not cached.is_file():
        return None
    try:
        with np.load(cached, allow_pickle=False) as z:
            older = [k for k in extra if k not in z.files] if {"xyz", "rgb"} <= set(z.files) else []
            got = None if older else {k: np.asarray(z[k]) for k in ("xyz", "rgb", *extra)}
        if got is None:         # (written by an earlier version that computed them differently: not damaged)
            say(f"note: {cached}: initial points computed by an earlier version (no {', '.join(older)}); "
                "computing them again")
            with contextlib.suppress(OSError):
                cached.unlink()
            return None
        xyz, rgb = got["xyz"], got["rgb"]
        if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape or not np.all(np.isfinite(xyz)):
            raise ValueError(f"points of shape {xyz.shape} with colours of shape {rgb.shape}, or not finite")
        if "seconds" in got:
            json.loads(str(got["seconds"]))
        return got
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        why = " ".join(str(e).split())[:120] or type(e).__name__
        say(f"note: {cached}: damaged cache of initial points ({why}); computing them again")
        with contextlib.suppress(OSError):
            cached.unlink()
        return None


def triangulate(views, color_space: str, work: Path, cfg: TriangulateConfig = TriangulateConfig(), seed: int = 0,
                where: str = "dataset", log: Callable[[str], None] | None = None) -> Triangulated:
    """Triangulate points from ``views`` (a dataset's training views) in the folder ``work`` (created; its
    ``points.npz`` is the result, reused when present). See the module docstring."""
    work = Path(work)
    cached = work / "points.npz"
    say = log or (lambda line: None)
    z = load_cached_points(cached, ("seconds", "pairs", "verified"), say)
    if z is not None:
        result = Triangulated(z["xyz"], z["rgb"], json.loads(str(z["seconds"])), int(z["pairs"]),
                              int(z["verified"]), cached=True)
        say(f"initial points: {len(result.xyz):,} triangulated earlier, reused from {cached}")
        return result
    cameras = [v.camera for v in views]
    check_cameras(cameras, where)
    import pycolmap

    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(level, 2)
    _remove_abandoned(work)
    scratch = work / f"colmap-{os.getpid()}"     # (two runs sharing a cache do not share their work folder)
    try:
        result = _run(views, color_space, scratch, cfg, seed, where, say)
    except RuntimeError as e:                    # (pycolmap's: e.g. its database could not be written)
        raise OSError(f"{scratch}: pycolmap failed while triangulating ({' '.join(str(e).split())[:200]}); is the "
                      "disk full, or the folder not writable?") from None
    finally:
        pycolmap.logging.minloglevel = level
        shutil.rmtree(scratch, ignore_errors=True)
    with atomic_path(cached, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, xyz=result.xyz, rgb=result.rgb, seconds=json.dumps(result.seconds), pairs=result.pairs,
                     verified=result.verified_pairs)
    return result


def _run(views, color_space: str, scratch: Path, cfg: TriangulateConfig, seed: int, where: str,
         say) -> Triangulated:
    import pycolmap

    from ..imwrite import linear_to_srgb, srgb_to_linear, write_png

    seconds = {}
    images, masks = scratch / "images", scratch / "masks"
    images.mkdir(parents=True)
    db_path = scratch / "database.db"
    # names in list order when sorted (COLMAP numbers the images in sorted order), without spaces (pairs file)
    names = [f"{i:05d}.png" for i in range(len(views))]

    t0 = time.perf_counter()
    any_mask = False
    for name, v in zip(names, views):
        rgb, alpha = v.loader.load(v.image_path)
        shown = linear_to_srgb(np.maximum(rgb, 0.0)) if color_space == "linear" else rgb
        write_png(images / name, np.clip(shown, 0.0, 1.0))
        mask = np.ones(rgb.shape[:2], np.float32) if alpha is None else (alpha > 0.5).astype(np.float32)
        any_mask |= alpha is not None
        write_png(masks / f"{name}.png", mask)           # (COLMAP skips an image whose mask is missing)
    seconds["images"] = time.perf_counter() - t0
    say(f"triangulation [1/4] {len(views)} images written ({seconds['images']:.1f} s)")

    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    if any_mask:
        reader.mask_path = str(masks)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = -1
    extraction.use_gpu = False
    extraction.sift.max_num_features = cfg.max_features
    pycolmap.extract_features(db_path, images, image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(db_path)
    try:
        found = {im.name: im for im in db.read_all_images()}
        missing = [n for n in names if n not in found]
        if missing:
            raise NoPoints(f"{where}: pycolmap could not read {len(missing)} of the training images for "
                             f"triangulation (e.g. {views[names.index(missing[0])].name})")
        keypoints = 0
        for name, v in zip(names, views):
            c = db.read_camera(found[name].camera_id)
            cam = v.camera
            c.params = [cam.fx, cam.fy, cam.cx, cam.cy]
            c.has_prior_focal_length = True
            db.update_camera(c)
            keypoints += db.num_keypoints_for_image(found[name].image_id)
    finally:
        db.close()
    seconds["features"] = time.perf_counter() - t0
    say(f"triangulation [2/4] {keypoints:,} SIFT features ({seconds['features']:.1f} s)")
    if keypoints < 8 * len(views):
        raise NoPoints(f"{where}: the training images have too little texture to triangulate points from "
                         f"({keypoints} SIFT features in {len(views)} images)")

    t0 = time.perf_counter()
    pairs = choose_pairs([v.camera for v in views], cfg.neighbours, cfg.exhaustive_below)
    (scratch / "pairs.txt").write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = -1
    matching.use_gpu = False
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(scratch / "pairs.txt")
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    pycolmap.match_image_pairs(db_path, matching_options=matching, pairing_options=pairing,
                               verification_options=verification, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(db_path)
    try:
        _, inliers = db.read_two_view_geometry_num_inliers()
        verified = int(sum(1 for n in inliers if n >= 15))
        reconstruction = _reconstruction(db, views, names)
    finally:
        db.close()
    seconds["matching"] = time.perf_counter() - t0
    say(f"triangulation [3/4] {len(pairs):,} pairs matched, {verified:,} verified ({seconds['matching']:.1f} s)")

    t0 = time.perf_counter()
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.ba_refine_focal_length = options.ba_refine_principal_point = options.ba_refine_extra_params = False
    options.triangulation.ignore_two_view_tracks = False     # (its default drops every point seen by two images)
    (scratch / "sparse").mkdir()
    rec = pycolmap.triangulate_points(reconstruction, db_path, images, scratch / "sparse", clear_points=True,
                                      options=options, refine_intrinsics=False)
    found = rec.num_points3D()
    observations = pycolmap.ObservationManager(rec)
    observations.filter_all_points3D(cfg.max_reprojection_error, cfg.min_angle)
    observations.filter_points3D_with_short_tracks(cfg.min_track_length)
    points = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in points], np.float64).reshape(-1, 3).astype(np.float32)
    rgb = np.array([p.color for p in points], np.float32).reshape(-1, 3) / 255.0
    if color_space == "linear":
        rgb = srgb_to_linear(rgb).astype(np.float32)
    seconds["triangulation"] = time.perf_counter() - t0
    say(f"triangulation [4/4] {found:,} points, {len(xyz):,} kept (reprojection <= {cfg.max_reprojection_error:g} "
        f"px, angle >= {cfg.min_angle:g} deg, tracks >= {cfg.min_track_length}) ({seconds['triangulation']:.1f} s)")
    return Triangulated(xyz, rgb, seconds, len(pairs), verified)


def _remove_abandoned(work: Path) -> None:
    """Remove the work folders of triangulations whose process has ended (killed before it cleaned up)."""
    from ..io_utils import process_alive

    for p in work.glob("colmap-*") if work.is_dir() else ():
        pid = p.name.partition("-")[2]
        if pid.isdigit() and not process_alive(int(pid)):
            shutil.rmtree(p, ignore_errors=True)


def _reconstruction(db, views, names):
    """A ``pycolmap.Reconstruction`` of our cameras (already in the database) and poses, every frame registered: its
    ids are the database's, as ``triangulate_points`` needs (it remaps only images, by name)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    for camera in db.read_all_cameras():
        rec.add_camera(camera)
    for rig in db.read_all_rigs():
        rec.add_rig(rig)
    by_id = {im.image_id: im for im in db.read_all_images()}
    index = {n: i for i, n in enumerate(names)}
    frames = db.read_all_frames()
    for frame in frames:
        (data_id,) = frame.image_ids             # (one image per frame: one camera per image)
        w2c = np.asarray(views[index[by_id[data_id.id].name]].camera.world_to_camera, np.float64)
        frame.rig_from_world = pycolmap.Rigid3d(w2c[:3, :4])
        rec.add_frame(frame)
    for image in by_id.values():
        rec.add_image(image)
    for frame in frames:
        rec.register_frame(frame.frame_id)
    return rec
