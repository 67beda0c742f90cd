"""The camera record: one pinhole camera in one convention (OpenCV axes, pixel centres at +0.5).

A camera-space point ``(x, y, z)`` (x right, y down, z forward) projects to the pixel coordinates
``(fx * x / z + cx, fy * y / z + cy)``; pixel ``(i, j)`` covers ``[i, i + 1) x [j, j + 1)`` and is sampled at its centre.
COLMAP uses the same convention; Mitsuba's film agrees once its camera axes (x left, y up, z forward) are flipped.

JSON form (``Camera.from_json`` / ``Camera.to_json``)::

    {"width": 800, "height": 600, "fx": 700.0, "fy": 700.0, "cx": 400.0, "cy": 300.0,
     "world_to_camera": [[r00, r01, r02, t0], [r10, r11, r12, t1], [r20, r21, r22, t2], [0, 0, 0, 1]],
     "name": "optional"}

``world_to_camera`` is row-major 4 x 4 (a list of 4 rows), OpenCV axes.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace

import numpy as np

from ..io_utils import atomic_write_text, read_json_object

# OpenGL/Blender camera axes (x right, y up, z back) <-> OpenCV (x right, y down, z forward): flip y and z.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
# Mitsuba camera axes (x left, y up, z forward) <-> OpenCV: flip x and y.
MI_TO_CV = np.diag([-1.0, -1.0, 1.0, 1.0])


def focal_from_fov(size: float, fov: float) -> float:
    """Focal length in pixels of an image ``size`` pixels across that spans the angle ``fov`` (radians)."""
    return size / (2.0 * math.tan(fov / 2.0))


def fov_from_focal(size: float, focal: float) -> float:
    """The angle (radians) that ``size`` pixels span at the focal length ``focal`` (pixels)."""
    return 2.0 * math.atan(size / (2.0 * focal))


def camera_center(world_to_camera: np.ndarray) -> np.ndarray:
    """The centre in world space, (3,), of a camera with this (4, 4) world-to-camera matrix."""
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    return -R.T @ t


def _as_matrix(m, what: str) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape == (3, 4):
        a = np.vstack([a, [0.0, 0.0, 0.0, 1.0]])
    if a.shape != (4, 4):
        raise ValueError(f"{what}: expected a 4x4 (or 3x4) matrix, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: matrix has non-finite entries")
    return a


#: How far a camera JSON's rotation may be from orthonormal (max |R R^T - I|, |det R - 1|): JSON written with
#: 6 significant digits passes, a scaled or sheared matrix does not.
RIGID_TOLERANCE = 1e-4


def _check_rigid(m: np.ndarray, what: str) -> None:
    r = m[:3, :3]
    off = float(np.abs(r @ r.T - np.eye(3)).max())
    det = float(np.linalg.det(r))
    if off > RIGID_TOLERANCE or abs(det - 1.0) > RIGID_TOLERANCE:
        kind = "a reflection" if det < 0 else "not a rotation (scaled or sheared)"
        raise ValueError(f"{what}: the upper-left 3x3 is {kind}: |R R^T - I| = {off:.3g}, det R = {det:.6g} (a "
                         "rigid world-to-camera matrix is needed)")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOLERANCE):
        raise ValueError(f"{what}: the last row must be 0 0 0 1, got {' '.join(f'{v:g}' for v in m[3])}")


#: focal lengths fx, fy further apart than this factor are reported (:func:`intrinsics_problem`): cameras have square
#: pixels, nearly always; a reconstruction that registered too few images can give far other values
FOCAL_RATIO_LIMIT = 1.2


def intrinsics_problem(cam: "Camera") -> str | None:
    """One line when the camera's focal lengths differ by more than :data:`FOCAL_RATIO_LIMIT` (pixels far from
    square: a reconstruction likely gone wrong), else None."""
    ratio = max(cam.fx, cam.fy) / min(cam.fx, cam.fy)
    if ratio <= FOCAL_RATIO_LIMIT:
        return None
    return (f"camera {cam.name!r}: fx {cam.fx:.6g} and fy {cam.fy:.6g} differ by a factor of {ratio:.2f} (pixels "
            "that are not square); a structure-from-motion reconstruction from too few registered images gives such "
            "cameras: check it")


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics in pixels, extrinsics as a world-to-camera matrix in OpenCV axes."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: np.ndarray = field(repr=False)  # (4, 4) float64, OpenCV axes
    name: str = ""

    def __post_init__(self):
        object.__setattr__(self, "world_to_camera", _as_matrix(self.world_to_camera, f"camera {self.name!r}"))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for k in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, k))
            if not math.isfinite(v):
                raise ValueError(f"camera {self.name!r}: {k} is not finite")
            object.__setattr__(self, k, v)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera {self.name!r}: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    # ---------------------------------------------------------------- derived quantities
    @property
    def camera_to_world(self) -> np.ndarray:
        return np.linalg.inv(self.world_to_camera)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world space, (3,)."""
        return camera_center(self.world_to_camera)

    @property
    def fov_x(self) -> float:
        return fov_from_focal(self.width, self.fx)

    @property
    def fov_y(self) -> float:
        return fov_from_focal(self.height, self.fy)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N, 3) -> (pixel coordinates (N, 2), camera-space depth z (N,))."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        pc = p @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], axis=1)
        return uv, z

    def sees(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Of points projected by :meth:`project`, those in front of the camera and inside its image (edges
        included): (N,) bool."""
        return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= self.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= self.height)

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera for an image resampled to ``width x height`` (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
                       cx=self.cx * sx, cy=self.cy * sy)

    # ---------------------------------------------------------------- JSON
    def to_dict(self) -> dict:
        d = {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx,
             "cy": self.cy, "world_to_camera": self.world_to_camera.tolist()}
        if self.name:
            d["name"] = self.name
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera") -> "Camera":
        """A camera from the fields of a camera JSON, each checked (ValueError naming ``source`` and the field):
        whole positive sizes, finite positive focal lengths, a finite principal point, and a rigid
        ``world_to_camera`` (a rotation: orthonormal with determinant +1 to :data:`RIGID_TOLERANCE`, a finite
        translation, a last row 0 0 0 1)."""
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy", "world_to_camera") if k not in d]
        if missing:
            raise ValueError(f"{source}: missing camera field(s) {', '.join(missing)}")
        for k in ("width", "height"):
            v = d[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer() or v < 1:
                raise ValueError(f"{source}: {k} must be a whole number of pixels >= 1, got {json.dumps(v)[:40]}")
        for k in ("fx", "fy", "cx", "cy"):
            v = d[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{source}: {k} must be a finite number, got {json.dumps(v)[:40]}")
        name = d.get("name", "")
        if not isinstance(name, str):
            raise ValueError(f"{source}: name must be a string, got {json.dumps(name)[:40]}")
        try:
            m = _as_matrix(d["world_to_camera"], "world_to_camera")
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: {e}") from None
        _check_rigid(m, f"{source}: world_to_camera")
        try:
            return cls(width=int(d["width"]), height=int(d["height"]), fx=d["fx"], fy=d["fy"], cx=d["cx"],
                       cy=d["cy"], world_to_camera=m, name=name)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: {e}") from None

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> "Camera":
        path = os.fspath(path)
        d = read_json_object(path, "camera file", "a JSON object with camera fields")
        return cls.from_dict(d, source=path)

    def to_json(self, path: str | os.PathLike) -> None:
        atomic_write_text(path, json.dumps(self.to_dict(), indent=2))

    # ---------------------------------------------------------------- other conventions
    @classmethod
    def from_camera_to_world_gl(cls, c2w_gl, width: int, height: int, fx: float, fy: float,
                                cx: float, cy: float, name: str = "") -> "Camera":
        """From an OpenGL/Blender/NeRF camera-to-world matrix (x right, y up, z back)."""
        c2w_cv = _as_matrix(c2w_gl, f"camera {name!r}") @ GL_TO_CV
        return cls(width, height, fx, fy, cx, cy, np.linalg.inv(c2w_cv), name)

    def to_mitsuba(self, near_clip: float = 0.01, far_clip: float = 1e4, rel_tol: float = 1e-3) -> dict:
        """A ``perspective`` sensor dictionary for ``mi.load_dict`` with the same pixel geometry.

        Mitsuba's perspective sensor has square pixels: ``fx`` and ``fy`` must agree to ``rel_tol``."""
        import mitsuba as mi

        if abs(self.fx - self.fy) > rel_tol * self.fx:
            raise ValueError(f"camera {self.name!r}: Mitsuba's perspective sensor needs square pixels, "
                             f"got fx={self.fx} fy={self.fy}")
        to_world = self.camera_to_world @ MI_TO_CV
        return {
            "type": "perspective",
            "fov_axis": "x",
            "fov": math.degrees(self.fov_x),
            "principal_point_offset_x": (self.width / 2.0 - self.cx) / self.width,
            "principal_point_offset_y": (self.height / 2.0 - self.cy) / self.height,
            "near_clip": near_clip,
            "far_clip": far_clip,
            "to_world": mi.ScalarTransform4f(to_world.tolist()),
            "film": {"type": "hdrfilm", "width": self.width, "height": self.height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgba"},
        }

    @classmethod
    def from_mitsuba(cls, sensor, name: str = "") -> "Camera":
        """From a loaded Mitsuba ``perspective`` sensor (any variant)."""
        import mitsuba as mi

        params = mi.traverse(sensor)
        size = sensor.film().size()
        width, height = int(size[0]), int(size[1])
        fov_x = math.radians(float(params["x_fov"][0] if hasattr(params["x_fov"], "__len__") else params["x_fov"]))
        fx = focal_from_fov(width, fov_x)
        off_x = float(params["principal_point_offset_x"][0]) if "principal_point_offset_x" in params else 0.0
        off_y = float(params["principal_point_offset_y"][0]) if "principal_point_offset_y" in params else 0.0
        to_world = np.array(mi.ScalarTransform4f(params["to_world"]).matrix, dtype=np.float64) \
            if not hasattr(params["to_world"], "matrix") else np.array(params["to_world"].matrix, dtype=np.float64)
        to_world = to_world.reshape(4, 4)
        c2w_cv = to_world @ MI_TO_CV
        return cls(width, height, fx, fx, width / 2.0 - off_x * width, height / 2.0 - off_y * height,
                   np.linalg.inv(c2w_cv), name or sensor.id())
