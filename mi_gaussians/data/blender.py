"""Parse NeRF-style ``transforms*.json`` files: Blender/NeRF-synthetic and instant-ngp / nerfstudio.

Format (all lengths in pixels, principal point in COLMAP's convention, pixel centres at +0.5)::

    {"camera_angle_x": 0.69,                      # horizontal FOV (rad); or "fl_x" (and "fl_y")
     "camera_angle_y": ...,                       # optional; fy = fx when neither fl_y nor this is given
     "fl_x": ..., "fl_y": ..., "cx": ..., "cy": ..., "w": ..., "h": ...,   # optional, global or per frame
     "k1": ..., "k2": ..., "p1": ..., "p2": ..., "k3": ...,                # optional OpenCV distortion
     "frames": [{"file_path": "./train/r_0", "transform_matrix": [[...4x4 camera-to-world, OpenGL axes...]]}]}

Per-frame keys override global ones. Without ``w``/``h`` the size comes from the image header; without ``cx``/``cy``
the principal point is the image centre (the NeRF-synthetic convention, the only case where it is assumed).
``file_path`` may omit the extension (tried: ``.png``, ``.jpg``, ``.jpeg``, ``.exr``). Fisheye models
(``camera_model`` OPENCV_FISHEYE / EQUIRECTANGULAR, ``is_fisheye``) are refused.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io_utils import read_json_object
from .camera import focal_from_fov
from .images import image_size, resolve_image_file


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics at the json's image size, plus optional distortion as a COLMAP model.

    ``distortion`` is None or (COLMAP model name, its full parameter tuple), e.g.
    ("OPENCV", (fx, fy, cx, cy, k1, k2, p1, p2))."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[str, tuple[float, ...]] | None = None


@dataclass(frozen=True)
class FrameRecord:
    """One frame of a transforms file. ``name`` is the image path relative to the json's folder (posix, with
    extension); ``exists`` tells whether the image file is there and ``file_size`` is its (width, height) from the
    header (None when missing); ``intrinsics`` is None only when the image is missing and the json gives no size."""

    index: int
    name: str
    image_path: Path
    exists: bool
    file_size: tuple[int, int] | None
    camera_to_world_gl: np.ndarray = field(repr=False)
    intrinsics: Intrinsics | None


def read_transforms(path: str | os.PathLike) -> dict:
    """Load a transforms json as a dict with a non-empty ``frames`` list; ``ValueError`` naming the file otherwise."""
    path = Path(path)
    d = read_json_object(path, "file", "a JSON object with a 'frames' list")
    frames = d.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{path}: no 'frames' list (or it is empty)")
    return d


def _number(v, what: str, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{where}: {what} must be a number, got {v!r}")
    x = float(v)
    if not math.isfinite(x):
        raise ValueError(f"{where}: {what} is not finite ({v!r})")
    return x


def _intrinsics(meta: dict, frame: dict, size: tuple[int, int] | None, where: str) -> Intrinsics | None:
    def get(key):
        v = frame.get(key, meta.get(key))
        return None if v is None else _number(v, key, where)

    if str(frame.get("camera_model", meta.get("camera_model", "OPENCV"))).upper() not in ("OPENCV", "PINHOLE") \
            or frame.get("is_fisheye", meta.get("is_fisheye", False)):
        model = frame.get("camera_model", meta.get("camera_model", "fisheye"))
        raise ValueError(f"{where}: unsupported camera model {model} (only pinhole and OpenCV-distorted "
                         "perspective cameras)")
    w, h = get("w"), get("h")
    if w is None or h is None:
        if size is None:
            return None
        w, h = size
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise ValueError(f"{where}: image size w={w}, h={h} is not a positive integer size")
    w, h = int(w), int(h)
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        ax = get("camera_angle_x")
        if ax is None:
            raise ValueError(f"{where}: no focal length (need 'fl_x' or 'camera_angle_x')")
        if not 0.0 < ax < math.pi:
            raise ValueError(f"{where}: camera_angle_x={ax} is not in (0, pi)")
        fx = focal_from_fov(w, ax)
    if fy is None:
        ay = get("camera_angle_y")
        fy = focal_from_fov(h, ay) if ay is not None and 0.0 < ay < math.pi else fx
    if fx <= 0 or fy <= 0:
        raise ValueError(f"{where}: focal lengths must be positive, got fl_x={fx}, fl_y={fy}")
    cx, cy = get("cx"), get("cy")
    cx = w / 2.0 if cx is None else cx
    cy = h / 2.0 if cy is None else cy
    k = {name: (get(name) or 0.0) for name in ("k1", "k2", "k3", "k4", "p1", "p2")}
    distortion = None
    if k["k4"] != 0.0:
        raise ValueError(f"{where}: k4 without a fisheye model is ambiguous (unsupported camera model)")
    if k["k3"] != 0.0:
        distortion = ("FULL_OPENCV", (fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"], k["k3"], 0.0, 0.0, 0.0))
    elif any(k[n] != 0.0 for n in ("k1", "k2", "p1", "p2")):
        distortion = ("OPENCV", (fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"]))
    return Intrinsics(w, h, fx, fy, cx, cy, distortion)


def read_frames(path: str | os.PathLike) -> list[FrameRecord]:
    """Parse every frame of one transforms file (image paths resolved against the json's folder).

    Missing images are reported through ``FrameRecord.exists``; the caller decides whether that is an error."""
    path = Path(path)
    meta = read_transforms(path)
    base = path.parent
    records: list[FrameRecord] = []
    for i, fr in enumerate(meta["frames"]):
        where = f"{path}: frame {i}"
        if not isinstance(fr, dict):
            raise ValueError(f"{where}: expected an object with 'file_path' and 'transform_matrix'")
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise ValueError(f"{where}: missing 'file_path'")
        where = f"{path}: frame {i} ({fp})"
        if "transform_matrix" not in fr:
            raise ValueError(f"{where}: missing 'transform_matrix'")
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: transform_matrix is not a numeric matrix") from None
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4):
            raise ValueError(f"{where}: transform_matrix must be 4x4, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise ValueError(f"{where}: transform_matrix has non-finite entries (NaN/inf)")
        R = m[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0 or np.any(m[3] != [0, 0, 0, 1]):
            raise ValueError(f"{where}: transform_matrix is not a rigid camera-to-world transform "
                             "(rotation not orthonormal, a reflection, or a projective last row)")
        image_path, exists = resolve_image_file(base, fp)
        size = image_size(image_path) if exists else None
        intr = _intrinsics(meta, fr, size, where)
        name = image_path.relative_to(base).as_posix() if image_path.is_relative_to(base) else image_path.name
        records.append(FrameRecord(i, os.path.normpath(name).replace(os.sep, "/"), image_path, exists, size, m, intr))
    return records
