"""Read a COLMAP sparse model (``cameras``, ``images``, ``points3D``; ``.bin`` or ``.txt``) with pycolmap.

Read-only. Poses are world-to-camera in OpenCV axes (COLMAP's own convention), pixel centres at +0.5, so a pinhole
COLMAP camera is a :class:`~mi_gaussians.data.camera.Camera` as is. Distorted perspective models are accepted and
undistorted later (see ``images.Undistorter``); fisheye and other non-perspective models are refused.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Pinhole models: used as they are.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
# Perspective models with lens distortion: undistorted in memory to a PINHOLE camera, as COLMAP's image_undistorter does.
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
SUPPORTED_MODELS = PINHOLE_MODELS + DISTORTED_MODELS

_MODEL_FILES = ("cameras", "images", "points3D")


@dataclass(frozen=True)
class ColmapCamera:
    """One COLMAP camera: model name, the image size its parameters belong to, parameters in COLMAP order."""

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]

    @property
    def is_pinhole(self) -> bool:
        return self.model in PINHOLE_MODELS

    def pinhole_intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of a PINHOLE / SIMPLE_PINHOLE camera."""
        p = self.params
        if self.model == "PINHOLE":
            return p[0], p[1], p[2], p[3]
        if self.model == "SIMPLE_PINHOLE":
            return p[0], p[0], p[1], p[2]
        raise ValueError(f"COLMAP camera {self.camera_id}: {self.model} is not a pinhole model")


@dataclass(frozen=True)
class ColmapImage:
    """One registered image: its file name (relative to the image folder), camera and world-to-camera pose (4, 4)."""

    image_id: int
    name: str
    camera_id: int
    world_to_camera: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class ColmapModel:
    """A parsed sparse model. ``images`` is sorted by name; points are (M, 3) float32, colours in [0, 1]."""

    path: Path
    extension: str                      # ".bin" or ".txt"
    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points_xyz: np.ndarray = field(repr=False)
    points_rgb: np.ndarray = field(repr=False)

    def file(self, stem: str) -> Path:
        """Path of one of the model files, e.g. ``file("cameras")``."""
        return self.path / f"{stem}{self.extension}"


def find_model_dir(root: str | os.PathLike) -> Path | None:
    """The sparse model folder of a scene: ``root/sparse/0`` or ``root/sparse`` (holding ``cameras.bin|txt``)."""
    root = Path(root)
    for d in (root / "sparse" / "0", root / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


def _model_extension(model_dir: Path) -> str:
    for ext in (".bin", ".txt"):
        present = [(model_dir / f"{s}{ext}").is_file() for s in _MODEL_FILES]
        if all(present):
            return ext
        if any(present):
            missing = [f"{s}{ext}" for s, ok in zip(_MODEL_FILES, present) if not ok]
            raise ValueError(f"{model_dir}: incomplete COLMAP model, missing {', '.join(missing)}")
    raise ValueError(f"{model_dir}: no COLMAP model (cameras, images, points3D as .bin or .txt)")


def read_model(model_dir: str | os.PathLike, with_points: bool = True) -> ColmapModel:
    """Read and validate a COLMAP sparse model.

    Raises ``ValueError`` naming the offending file for: missing/unreadable files, camera models outside
    ``SUPPORTED_MODELS``, non-finite poses, images referring to unknown cameras, no registered images.
    Images without a pose (not registered) are left out.
    """
    import pycolmap

    model_dir = Path(model_dir)
    ext = _model_extension(model_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with its C++ check text
        msg = " ".join(str(e).split())
        raise ValueError(f"{model_dir}: cannot read the COLMAP model ({', '.join(s + ext for s in _MODEL_FILES)}): "
                         f"{msg}") from None
    cam_file, img_file = model_dir / f"cameras{ext}", model_dir / f"images{ext}"

    cameras: dict[int, ColmapCamera] = {}
    for cid, c in rec.cameras.items():
        model = c.model.name if hasattr(c.model, "name") else str(c.model)
        if model not in SUPPORTED_MODELS:
            raise ValueError(f"{cam_file}: unsupported COLMAP camera model {model} (camera {cid}); supported: "
                             f"{', '.join(SUPPORTED_MODELS)} (undistort fisheye captures to pinhole images first)")
        params = tuple(float(p) for p in c.params)
        if not np.all(np.isfinite(params)) or c.width <= 0 or c.height <= 0:
            raise ValueError(f"{cam_file}: camera {cid} has invalid size or parameters")
        cameras[int(cid)] = ColmapCamera(int(cid), model, int(c.width), int(c.height), params)

    images: list[ColmapImage] = []
    for iid, im in rec.images.items():
        if not im.has_pose:
            continue
        if int(im.camera_id) not in cameras:
            raise ValueError(f"{img_file}: image {im.name!r} refers to unknown camera {im.camera_id}")
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        if not np.all(np.isfinite(w2c)):
            raise ValueError(f"{img_file}: image {im.name!r} has a non-finite pose")
        images.append(ColmapImage(int(iid), str(im.name), int(im.camera_id), w2c))
    if not images:
        raise ValueError(f"{img_file}: no registered images")
    images.sort(key=lambda i: i.name)

    xyz = np.zeros((0, 3), np.float32)
    rgb = np.zeros((0, 3), np.float32)
    if with_points and rec.num_points3D() > 0:
        pts = list(rec.points3D.values())
        xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
        rgb = np.array([p.color for p in pts], dtype=np.float32).reshape(-1, 3) / 255.0
        if not np.all(np.isfinite(xyz)):
            raise ValueError(f"{model_dir / ('points3D' + ext)}: non-finite point coordinates")
        xyz = xyz.astype(np.float32)
    return ColmapModel(model_dir, ext, cameras, images, xyz, rgb)
