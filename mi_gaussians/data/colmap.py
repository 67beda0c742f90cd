"""Read a COLMAP sparse model (``cameras``, ``images``, ``points3D``; ``.bin`` or ``.txt``).

Read-only. Poses are world-to-camera in OpenCV axes (COLMAP's own convention), pixel centres at +0.5, so a pinhole
COLMAP camera is a :class:`~mi_gaussians.data.camera.Camera` as is. Distorted perspective models are accepted and
undistorted later (see ``images.Undistorter``); fisheye and other non-perspective models are refused.

The files are parsed here, in the layout of COLMAP's ``doc/format.rst`` (and its ``read_write_model.py``), rather
than by ``pycolmap.Reconstruction``: pycolmap reports a malformed file as a C++ ``Check failed: line_stream1 >> ...``
without the file or line, and some mistakes surface as unrelated messages ("Rig with ID 7 does not exist" for an image
naming an unknown camera). Every problem here is one ``ValueError`` naming the file and the line (text) or the record
and byte offset (binary). The tests compare the result with pycolmap's on every shared dataset.
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Pinhole models: used as they are.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
# Perspective models with lens distortion: undistorted in memory to a PINHOLE camera, as COLMAP's image_undistorter does.
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
SUPPORTED_MODELS = PINHOLE_MODELS + DISTORTED_MODELS

#: COLMAP's model ids (``CameraModelId``) and parameter counts of the supported models.
_MODEL_IDS = {0: "SIMPLE_PINHOLE", 1: "PINHOLE", 2: "SIMPLE_RADIAL", 3: "RADIAL", 4: "OPENCV", 6: "FULL_OPENCV"}
_PARAM_COUNTS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}

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


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix of the non-zero quaternion (w, x, y, z), normalised first (as COLMAP's reader does)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.abs(q).max()             # first to a largest component of 1: the norm neither overflows nor underflows
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quaternion(R) -> np.ndarray:
    """The unit quaternion (w, x, y, z), w >= 0, of the rotation matrix ``R`` (the inverse of
    :func:`quaternion_to_matrix`; Shepperd's method, stable for every angle)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    i = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if i == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        j, k = i % 3 + 1, (i + 1) % 3 + 1          # the two other axes, 1-based as i
        s = 2.0 * math.sqrt(1.0 + R[i - 1, i - 1] - R[j - 1, j - 1] - R[k - 1, k - 1])
        q = [0.0] * 4
        q[0] = (R[k - 1, j - 1] - R[j - 1, k - 1]) / s
        q[i] = 0.25 * s
        q[j] = (R[j - 1, i - 1] + R[i - 1, j - 1]) / s
        q[k] = (R[k - 1, i - 1] + R[i - 1, k - 1]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


def images_text(names: list[str], world_to_cameras: list[np.ndarray], camera_ids: list[int]) -> str:
    """COLMAP's ``images.txt`` of these poses (no 2D points: each image's second line is empty)."""
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(names)}, mean observations per image: 0"]
    for iid, (name, m, cid) in enumerate(zip(names, world_to_cameras, camera_ids), start=1):
        q, t = matrix_to_quaternion(np.asarray(m)[:3, :3]), np.asarray(m, np.float64)[:3, 3]
        lines += [" ".join([str(iid), *(repr(float(v)) for v in (*q, *t)), str(cid), name]), ""]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------------- validation
def _camera(where: str, cid: int, model: str, width: int, height: int, params: list[float]) -> ColmapCamera:
    if model not in SUPPORTED_MODELS:
        raise ValueError(f"{where}: unsupported COLMAP camera model {model} (camera {cid}); supported: "
                         f"{', '.join(SUPPORTED_MODELS)} (undistort fisheye captures to pinhole images first)")
    if width <= 0 or height <= 0:
        raise ValueError(f"{where}: camera {cid} has the image size {width}x{height}")
    if not all(math.isfinite(p) for p in params):
        raise ValueError(f"{where}: camera {cid} has non-finite parameters")
    return ColmapCamera(cid, model, width, height, tuple(params))


def _image(where: str, iid: int, q, t, cid: int, name: str, cameras: dict) -> ColmapImage:
    if cid not in cameras:
        raise ValueError(f"{where}: image {name!r} refers to camera {cid}, which cameras does not define "
                         f"(cameras: {', '.join(map(str, sorted(cameras)[:10]))})")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise ValueError(f"{where}: image {name!r} has a non-finite pose")
    if not np.any(np.asarray(q) != 0):
        raise ValueError(f"{where}: image {name!r} has a zero rotation quaternion")
    w2c = np.eye(4)
    w2c[:3, :3] = quaternion_to_matrix(q)
    w2c[:3, 3] = t
    return ColmapImage(iid, name, cid, w2c)


def _unique(where: str, kind: str, seen: set, key) -> None:
    if key in seen:
        raise ValueError(f"{where}: duplicate {kind} {key!r}")
    seen.add(key)


# ---------------------------------------------------------------------------------------------------- text
def _text_lines(path: Path):
    """(line number, whitespace-split tokens) of every line, comments and blank lines included (images.txt needs
    the blank points line of an image without observations)."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ValueError(f"{path}: cannot read file: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        raise ValueError(f"{path}, line {line}: not UTF-8 text") from None
    for n, line in enumerate(text.splitlines(), 1):
        yield n, line.split()


def _is_data(tokens) -> bool:
    return bool(tokens) and not tokens[0].startswith("#")


def _num(where: str, token: str, what: str, kind=float):
    try:
        v = kind(token)
    except ValueError:
        raise ValueError(f"{where}: {what} is {token[:40]!r}, not a{'n integer' if kind is int else ' number'}") \
            from None
    return v


def _read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    cameras: dict[int, ColmapCamera] = {}
    for n, tok in _text_lines(path):
        if not _is_data(tok):
            continue
        where = f"{path}, line {n}"
        if len(tok) < 4:
            raise ValueError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {len(tok)} fields")
        cid = _num(where, tok[0], "CAMERA_ID", int)
        model = tok[1]
        width, height = (_num(where, tok[i], k, int) for i, k in ((2, "WIDTH"), (3, "HEIGHT")))
        params = [_num(where, p, f"parameter {i + 1}") for i, p in enumerate(tok[4:])]
        if model in _PARAM_COUNTS and len(params) != _PARAM_COUNTS[model]:
            raise ValueError(f"{where}: a {model} camera has {_PARAM_COUNTS[model]} parameters, got {len(params)}")
        if cid in cameras:
            raise ValueError(f"{where}: duplicate CAMERA_ID {cid!r}")
        cameras[cid] = _camera(where, cid, model, width, height, params)
    return cameras


def _read_images_text(path: Path, cameras: dict) -> list[ColmapImage]:
    images: list[ColmapImage] = []
    ids: set = set()
    lines = iter(_text_lines(path))
    for n, tok in lines:
        if not _is_data(tok):
            continue
        where = f"{path}, line {n}"
        if len(tok) != 10:
            raise ValueError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (10 fields, names "
                             f"without spaces), got {len(tok)} fields")
        iid = _num(where, tok[0], "IMAGE_ID", int)
        q = [_num(where, v, k) for v, k in zip(tok[1:5], ("QW", "QX", "QY", "QZ"))]
        t = [_num(where, v, k) for v, k in zip(tok[5:8], ("TX", "TY", "TZ"))]
        cid = _num(where, tok[8], "CAMERA_ID", int)
        _unique(where, "IMAGE_ID", ids, iid)
        images.append(_image(where, iid, q, t, cid, tok[9], cameras))
        # the second line of an image: its 2D points as X Y POINT3D_ID triples (may be empty)
        n2, pts = next(lines, (n + 1, None))
        where2 = f"{path}, line {n2}"
        if pts is None:
            raise ValueError(f"{where2}: the file ends before the points line of image {tok[9]!r}")
        if len(pts) % 3:
            raise ValueError(f"{where2}: the points of image {tok[9]!r} are not X Y POINT3D_ID triples "
                             f"({len(pts)} values)")
        for i in range(0, len(pts), 3):
            _num(where2, pts[i], "a point's X")
            _num(where2, pts[i + 1], "a point's Y")
            _num(where2, pts[i + 2], "a POINT3D_ID", int)
    return images


def _read_points_text(path: Path) -> tuple[np.ndarray, np.ndarray]:
    xyz, rgb = [], []
    ids: set = set()
    for n, tok in _text_lines(path):
        if not _is_data(tok):
            continue
        where = f"{path}, line {n}"
        if len(tok) < 8 or (len(tok) - 8) % 2:
            raise ValueError(f"{where}: expected POINT3D_ID X Y Z R G B ERROR and IMAGE_ID POINT2D_IDX pairs, "
                             f"got {len(tok)} fields")
        pid = _num(where, tok[0], "POINT3D_ID", int)
        p = [_num(where, v, k) for v, k in zip(tok[1:4], "XYZ")]
        c = [_num(where, v, k, int) for v, k in zip(tok[4:7], "RGB")]
        _num(where, tok[7], "ERROR")
        for v in tok[8:]:
            _num(where, v, "a track entry", int)
        if not all(0 <= v <= 255 for v in c):
            raise ValueError(f"{where}: colour {c} is outside 0..255")
        _unique(where, "POINT3D_ID", ids, pid)
        xyz.append(p)
        rgb.append(c)
    return np.array(xyz, np.float64).reshape(-1, 3), np.array(rgb, np.float32).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------------- binary
def _model_name(model_id: int) -> str:
    """`` = NAME`` of a COLMAP model id pycolmap knows, else an empty string."""
    import pycolmap

    try:
        name = pycolmap.CameraModelId(model_id).name
    except (ValueError, TypeError, OverflowError):
        return ""
    return f" = {name}" if name.isidentifier() else ""      # (pycolmap names an unknown id '???')


class _Binary:
    """A bounds-checked little-endian reader over one file's bytes; errors name the file, record and byte offset."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.data = path.read_bytes()
        except OSError as e:
            raise ValueError(f"{path}: cannot read file: {e.strerror or e}") from None
        self.pos = 0
        self.record = ""

    def error(self, problem: str) -> ValueError:
        record = f"{self.record}, " if self.record else ""
        return ValueError(f"{self.path}: {problem} ({record}byte {self.pos} of {len(self.data)})")

    def read(self, fmt: str):
        s = struct.Struct("<" + fmt)
        if self.pos + s.size > len(self.data):
            raise self.error("truncated file")
        out = s.unpack_from(self.data, self.pos)
        self.pos += s.size
        return out

    def skip(self, count: int, size: int, what: str) -> None:
        if count * size > len(self.data) - self.pos:
            raise self.error(f"{count} {what} do not fit in the rest of the file")
        self.pos += count * size

    def count(self, what: str, min_size: int) -> int:
        (n,) = self.read("Q")
        if n * min_size > len(self.data) - self.pos:
            raise self.error(f"{n} {what} do not fit in the file")
        return n

    def name(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise self.error("truncated file: an image name has no terminating NUL byte")
        raw, self.pos = self.data[self.pos:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise self.error("an image name is not UTF-8") from None

    def finish(self) -> None:
        self.record = ""
        if self.pos != len(self.data):
            raise self.error(f"{len(self.data) - self.pos} bytes after the last record")


def _read_cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    f = _Binary(path)
    cameras: dict[int, ColmapCamera] = {}
    for i in range(f.count("cameras", 24)):
        f.record = f"camera record {i}"
        cid, model_id, width, height = f.read("IiQQ")
        model = _MODEL_IDS.get(model_id)
        if model is None:
            raise f.error(f"unsupported COLMAP camera model id {model_id}{_model_name(model_id)} (camera {cid}); "
                          "supported: " + ", ".join(f"{k} {v}" for k, v in _MODEL_IDS.items())
                          + " (undistort fisheye captures to pinhole images first)")
        params = list(f.read("d" * _PARAM_COUNTS[model]))
        if cid in cameras:
            raise f.error(f"duplicate camera id {cid}")
        cameras[cid] = _camera(f"{path} (camera record {i})", cid, model, width, height, params)
    f.finish()
    return cameras


def _read_images_bin(path: Path, cameras: dict) -> list[ColmapImage]:
    f = _Binary(path)
    images: list[ColmapImage] = []
    ids: set = set()
    for i in range(f.count("images", 69)):
        f.record = f"image record {i}"
        iid, *qt, cid = f.read("I7dI")
        name = f.name()
        f.skip(f.read("Q")[0], 24, "2D points")
        if not name:
            raise f.error("empty image name")
        if iid in ids:
            raise f.error(f"duplicate image id {iid}")
        ids.add(iid)
        images.append(_image(f"{path} (image record {i})", iid, qt[:4], qt[4:], cid, name, cameras))
    f.finish()
    return images


def _read_points_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    f = _Binary(path)
    n = f.count("points", 43)
    xyz = np.empty((n, 3), np.float64)
    rgb = np.empty((n, 3), np.float32)
    record = struct.Struct("<Q3d3BdQ")
    data = f.data
    for i in range(n):
        if f.pos + record.size > len(data):
            f.record = f"point record {i}"
            raise f.error("truncated file")
        _, x, y, z, r, g, b, _, track = record.unpack_from(data, f.pos)
        f.pos += record.size
        xyz[i] = x, y, z
        rgb[i] = r, g, b
        if track * 8 > len(data) - f.pos:
            f.record = f"point record {i}"
            raise f.error(f"a track of {track} entries does not fit in the rest of the file")
        f.pos += track * 8
    f.finish()
    return xyz, rgb


# ---------------------------------------------------------------------------------------------------- model
def read_model(model_dir: str | os.PathLike, with_points: bool = True) -> ColmapModel:
    """Read and validate a COLMAP sparse model.

    Raises ``ValueError`` naming the offending file (and line, or record and byte offset) for: missing, unreadable or
    malformed files, camera models outside ``SUPPORTED_MODELS``, parameter counts that do not match the model,
    non-finite values, images referring to unknown cameras, duplicate ids, no images. Every image listed is registered
    (COLMAP writes only those).
    """
    model_dir = Path(model_dir)
    ext = _model_extension(model_dir)
    cam_file, img_file, pts_file = (model_dir / f"{s}{ext}" for s in _MODEL_FILES)
    binary = ext == ".bin"
    cameras = (_read_cameras_bin if binary else _read_cameras_text)(cam_file)
    images = (_read_images_bin if binary else _read_images_text)(img_file, cameras)
    if not images:
        raise ValueError(f"{img_file}: no registered images")
    images.sort(key=lambda i: i.name)

    xyz = np.zeros((0, 3), np.float32)
    rgb = np.zeros((0, 3), np.float32)
    if with_points:
        xyz, rgb = (_read_points_bin if binary else _read_points_text)(pts_file)
        with np.errstate(over="ignore", invalid="ignore"):
            xyz32 = xyz.astype(np.float32)
        if not np.all(np.isfinite(xyz32)):
            bad = int((~np.all(np.isfinite(xyz32), axis=1)).sum())
            raise ValueError(f"{pts_file}: {bad} point(s) with coordinates that are not finite in float32")
        xyz, rgb = xyz32, rgb / np.float32(255.0)
    return ColmapModel(model_dir, ext, cameras, images, xyz, rgb)
