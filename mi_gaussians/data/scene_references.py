"""Path-traced references of a Mitsuba scene dataset, cached as EXR files.

References are rendered with the scene's own integrator (``mi.render``; a box pixel filter and an RGBA film, so alpha
marks coverage) and cached as linear RGBA EXR files in ``cache_root/<key>/<split>/<camera>.exr``, with the exact
depth beside each (``<camera>.depth.npy``: float32 (H, W), the view-space z of the first surface hit through each
pixel's centre, found by Mitsuba's ray tracer -- what a depth AOV gives at the pixel centre -- and +inf where the ray
hits nothing), ``key`` (:func:`cache_key`) hashing the scene file, every file it references, its parameters, the
cameras, the sample count and the Mitsuba version. Each file is written atomically as soon as it is rendered, so an
interrupted run re-renders only what is missing, and a re-run renders nothing. ``rig.json`` beside them records the
cameras. Each reference has its own sampler seed (:func:`reference_seed`), so a reference rendered in another process
(a farm of Ray workers) is the same, bit for bit.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..imwrite import write_exr
from ..io_utils import atomic_path, atomic_write_text
from .camera import Camera
from .scene_file import parse_defines, referenced_files, scene_bbox
from .scene_rig import SceneViews

CACHE_VERSION = 1       # bump when how references are rendered changes (sampler, seeds, filter, clip planes)
RIG_FILE = "rig.json"
_TEST_SEED_OFFSET = 1_000_003


def reference_seed(split: str, index: int) -> int:
    """The sampler seed of the reference of camera ``index`` of ``split`` ('train' or 'test'): the same in every
    process, so references rendered anywhere are the same."""
    return index if split == "train" else _TEST_SEED_OFFSET + index


def cache_key(path: str | os.PathLike, views: SceneViews, defines=()) -> str:
    """Hash of the scene file, every file it references, its parameters (``defines``), the cameras, the sample count,
    the Mitsuba version and variant, and :data:`CACHE_VERSION`."""
    import mitsuba as mi

    h = hashlib.sha256()
    p = Path(path).resolve()
    h.update(p.read_bytes())
    for f in referenced_files(p, defines):
        h.update(str(f.relative_to(p.parent) if f.is_relative_to(p.parent) else f).encode())
        h.update(hashlib.sha256(f.read_bytes()).digest())
    rig = {"train": [c.to_dict() for c in views.train], "test": [c.to_dict() for c in views.test],
           "spp": views.spp, "mitsuba": mi.__version__, "variant": mi.variant(), "version": CACHE_VERSION,
           "defines": sorted(parse_defines(defines).items())}
    h.update(json.dumps(rig, sort_keys=True).encode())
    return h.hexdigest()[:16]


def write_rig_file(cache_dir: Path, path: Path, defines, key: str, views: SceneViews) -> None:
    """``cache_dir/rig.json``: the scene, its parameters, the key and the cameras (written once)."""
    rig_file = cache_dir / RIG_FILE
    if rig_file.is_file():
        return
    rig = {"scene": str(path.resolve()), "defines": list(defines), "key": key, "source": views.source,
           "spp": views.spp, "train": [c.to_dict() for c in views.train], "test": [c.to_dict() for c in views.test]}
    cache_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(rig_file, json.dumps(rig, indent=1) + "\n")


def _multijitter_count(spp: int) -> int:
    """The sample count Mitsuba's multijitter sampler uses for ``spp`` (it rounds up to a w x h grid)."""
    w = math.ceil(math.sqrt(spp))
    return w * math.ceil(spp / w)


def _reference_sensor(scene, cam: Camera, spp: int):
    """``cam`` as a Mitsuba sensor whose clip planes follow the scene's size: near 1e-4 of the bounding-box diagonal,
    far 10 times the farthest bounding-box corner."""
    import mitsuba as mi

    lo, hi = scene_bbox(scene)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    far = 10.0 * float(np.linalg.norm(corners - cam.center, axis=1).max())
    diag = float(np.linalg.norm(hi - lo))
    d = cam.to_mitsuba(near_clip=max(1e-4 * diag, 1e-7), far_clip=max(far, 1e-3))
    d["sampler"] = {"type": "multijitter", "sample_count": _multijitter_count(spp)}
    return mi.load_dict(d)


def render_reference(scene, cam: Camera, spp: int, seed: int) -> np.ndarray:
    """One path-traced reference: (H, W, 4) float32 linear RGB + alpha (box filter), with the scene's integrator."""
    import mitsuba as mi

    sensor = _reference_sensor(scene, cam, spp)
    img = np.array(mi.render(scene, sensor=sensor, spp=_multijitter_count(spp), seed=seed), dtype=np.float32)
    if img.ndim != 3 or img.shape[2] < 3:
        raise ValueError(f"the scene's integrator returned an image of shape {img.shape}, expected RGB(A)")
    if img.shape[2] == 3:
        img = np.concatenate([img, np.ones_like(img[..., :1])], axis=2)
    img = img[..., :4]
    if not np.all(np.isfinite(img)):
        bad = int((~np.isfinite(img)).any(axis=2).sum())
        raise ValueError(f"the reference of camera {cam.name!r} has {bad} non-finite pixels (NaN/Inf from the "
                         "scene's integrator)")
    return img


def reference_depth(scene, cam: Camera) -> np.ndarray:
    """(H, W) float32: view-space z (OpenCV, along the camera axis) of the first surface each pixel centre's ray hits
    (Mitsuba's ``Scene.ray_intersect``), +inf where it hits nothing."""
    import drjit as dr
    import mitsuba as mi

    W, H = cam.width, cam.height
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    norm = np.linalg.norm(d_cam, axis=1)
    R = cam.world_to_camera[:3, :3]
    d_world = (d_cam / norm[:, None]) @ R           # R^T d for each row
    o = cam.center
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(len(d_world), o[i], np.float32)) for i in range(3)]),
                   mi.Vector3f(*[mi.Float(d_world[:, i].astype(np.float32)) for i in range(3)]))
    with dr.suspend_grad():
        si = scene.ray_intersect(ray)
        t = np.array(dr.select(si.is_valid(), si.t, dr.inf), np.float64)
    return (t / norm).reshape(H, W).astype(np.float32)


def depth_path(exr: Path) -> Path:
    """The depth file beside the reference ``exr``."""
    return exr.with_name(exr.stem + ".depth.npy")


@dataclass(frozen=True)
class ReferenceJob:
    """One camera whose reference (``image``: the path-traced EXR) and/or exact depth (``depth``) are missing."""

    camera: Camera
    seed: int              # the sampler seed (:func:`reference_seed`)
    image: bool
    depth: bool


def render_jobs(scene, jobs: list[ReferenceJob], spp: int):
    """Yield (job index, (H, W, 4) reference or None, (H, W) depth or None) for each of ``jobs``, in order: what a
    farm does for its share of the views, with the scene it loaded once."""
    for k, job in enumerate(jobs):
        yield (k, render_reference(scene, job.camera, spp, job.seed) if job.image else None,
               reference_depth(scene, job.camera) if job.depth else None)


def render_references(scene, views: SceneViews, cache_dir: Path, progress: bool = True,
                      log: Callable[[str], None] | None = None, render: bool = True, farm=None) -> dict[str, Path]:
    """Render every camera that has no EXR (or no depth) in ``cache_dir`` yet; returns camera name -> EXR path.
    ``render=False``: render nothing, only say where each reference is (or would be). ``farm``: renders the jobs
    elsewhere (``farm.render(jobs, spp)`` yields what :func:`render_jobs` yields, in any order; e.g. Ray workers,
    :mod:`mi_gaussians.cluster.references`): each reference has its own seed, so where it is rendered does not
    change it."""
    from tqdm import tqdm

    cams = [("train", i, c) for i, c in enumerate(views.train)] + [("test", i, c) for i, c in enumerate(views.test)]
    paths = {c.name: cache_dir / split / f"{c.name}.exr" for split, _, c in cams}
    if not render:
        return paths
    jobs = [ReferenceJob(c, reference_seed(split, i), not paths[c.name].is_file(),
                         not depth_path(paths[c.name]).is_file()) for split, i, c in cams]
    jobs = [j for j in jobs if j.image or j.depth]
    todo = sum(j.image for j in jobs)
    if todo and log is not None:
        where = "" if farm is None else f" on {farm.describe()}"
        log(f"rendering {todo} of {len(cams)} references at {views.spp} spp{where} -> {cache_dir}")
    elif log is not None:
        log(f"reusing the {len(cams)} cached references in {cache_dir}")
    results = render_jobs(scene, jobs, views.spp) if farm is None else farm.render(jobs, views.spp)
    with tqdm(total=todo, desc="references", unit="view", disable=not progress or not todo) as bar:
        for k, image, depth in results:
            path = paths[jobs[k].camera.name]
            if image is not None:
                write_exr(path, image)
                bar.update(1)
            if depth is not None:
                with atomic_path(depth_path(path), suffix=".npy") as tmp:
                    with open(tmp, "wb") as f:
                        np.save(f, depth)
    return paths
