"""Path-traced references of a Mitsuba scene dataset, cached as EXR files.

References are rendered with the scene's own integrator (``mi.render``; a box pixel filter and an RGBA film, so alpha
marks coverage) and cached as linear RGBA EXR files in ``cache_root/<key>/<split>/<camera>.exr``, with the exact depth beside each
(``<camera>.depth.npy``: float32 (H, W), the view-space z of the first surface hit through each pixel's centre,
found by Mitsuba's ray tracer -- what a depth AOV gives at the pixel centre -- and +inf where the ray hits nothing), ``key``
(:func:`cache_key`) hashing the scene file, every file it references, its parameters, the cameras, the sample count
and the Mitsuba version. Each file is written atomically as soon as it is rendered, so an interrupted run re-renders
only what is missing, and a re-run renders nothing. ``rig.json`` beside them records the cameras.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
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


def render_references(scene, views: SceneViews, cache_dir: Path, progress: bool = True,
                      log: Callable[[str], None] | None = None, render: bool = True) -> dict[str, Path]:
    """Render every camera that has no EXR (or no depth) in ``cache_dir`` yet; returns camera name -> EXR path.
    ``render=False``: render nothing, only say where each reference is (or would be)."""
    from tqdm import tqdm

    cams = [("train", i, c) for i, c in enumerate(views.train)] + [("test", i, c) for i, c in enumerate(views.test)]
    paths = {c.name: cache_dir / split / f"{c.name}.exr" for split, _, c in cams}
    if not render:
        return paths
    todo = [(split, i, c) for split, i, c in cams if not paths[c.name].is_file()]
    if todo and log is not None:
        log(f"rendering {len(todo)} of {len(cams)} references at {views.spp} spp -> {cache_dir}")
    elif log is not None:
        log(f"reusing the {len(cams)} cached references in {cache_dir}")
    for split, i, c in tqdm(todo, desc="references", unit="view", disable=not progress or not todo):
        seed = i if split == "train" else _TEST_SEED_OFFSET + i
        write_exr(paths[c.name], render_reference(scene, c, views.spp, seed))
    for split, i, c in cams:
        target = depth_path(paths[c.name])
        if not target.is_file():
            with atomic_path(target, suffix=".npy") as tmp:
                with open(tmp, "wb") as f:
                    np.save(f, reference_depth(scene, c))
    return paths
