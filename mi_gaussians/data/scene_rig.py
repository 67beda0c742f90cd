"""The cameras of a Mitsuba scene dataset: the scene's own sensors, or a seeded rig around its bounding box.

A scene that declares several sensors is used as it is: its sensors are the cameras, every ``test_every``-th one
(index % test_every == 0, as the COLMAP split) held out. Otherwise a seeded rig is generated around the scene's
bounding box: ``views`` training and ``test_views`` held-out cameras on a hemisphere (elevation range above the plane
orthogonal to ``up``) or a full sphere, each set spread evenly (a Fibonacci lattice with its own random azimuth
offset, so test cameras are new poses), all looking at the centre of the bounding box. The rig takes the field of
view, film size, up direction and sample count of the scene's first sensor unless told otherwise; a first sensor
that is not perspective (orthographic) is refused unless a field of view is given.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import RIGS, DataConfig, SceneConfig
from .camera import Camera, focal_from_fov
from .scene_file import scene_bbox

FALLBACK_RESOLUTION = (256, 256)
FALLBACK_FOV = 40.0
FALLBACK_SPP = 128
FALLBACK_UP = (0.0, 1.0, 0.0)
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class SceneViews:
    """The cameras of a scene dataset and how the references are rendered."""

    train: list[Camera]
    test: list[Camera]
    spp: int
    source: str          # 'sensors' or 'hemisphere' / 'sphere' (generated)


# ---------------------------------------------------------------------------------------------------- geometry
def _snap_axis(v: np.ndarray) -> np.ndarray:
    k = int(np.argmax(np.abs(v)))
    out = np.zeros(3)
    out[k] = math.copysign(1.0, v[k])
    return out


def look_at_camera(origin, target, up, width: int, height: int, fov_x_deg: float, name: str) -> Camera:
    """A pinhole camera at ``origin`` looking at ``target`` (OpenCV axes: x right, y down, z forward)."""
    o, t, u = (np.asarray(a, dtype=np.float64).reshape(3) for a in (origin, target, up))
    forward = t - o
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, u)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError(f"camera {name!r}: the viewing direction is parallel to the up vector")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, o
    fx = focal_from_fov(width, math.radians(fov_x_deg))
    return Camera(width, height, fx, fx, width / 2.0, height / 2.0, np.linalg.inv(c2w), name)


def rig_directions(n: int, kind: str, up, elevation: tuple[float, float], azimuth_offset: float) -> np.ndarray:
    """``n`` unit directions spread evenly (Fibonacci lattice, equal area) over a hemisphere band (elevation range
    in degrees above the plane orthogonal to ``up``) or over a sphere (elevations -80 .. 80 degrees)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    lo, hi = (elevation if kind == "hemisphere" else (-80.0, 80.0))
    if not (-90.0 <= lo < hi <= 90.0):
        raise ValueError(f"elevation range must satisfy -90 <= low < high <= 90, got {lo}..{hi}")
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    k = np.arange(n) + 0.5
    s = math.sin(math.radians(lo)) + (math.sin(math.radians(hi)) - math.sin(math.radians(lo))) * k / n
    az = azimuth_offset + _GOLDEN_ANGLE * np.arange(n)
    c = np.sqrt(np.clip(1.0 - s * s, 0.0, 1.0))
    return (c * np.cos(az))[:, None] * e1 + (c * np.sin(az))[:, None] * e2 + s[:, None] * up


# ---------------------------------------------------------------------------------------------------- sensors
def _sensor_defaults(scene) -> dict:
    """fov / resolution / up / spp of the scene's first sensor (empty when it has none); a sensor that is not
    perspective (e.g. ``orthographic``) gives no fov and its class name as ``not_perspective``."""
    sensors = list(scene.sensors())
    if not sensors:
        return {}
    s = sensors[0]
    spp = int(s.sampler().sample_count()) if s.sampler() is not None else None
    if s.class_name() != "PerspectiveCamera":
        to_world = np.array(s.world_transform().matrix, dtype=np.float64).reshape(4, 4)
        size = tuple(int(v) for v in s.film().size())
        return {"resolution": size, "up": _snap_axis(to_world[:3, 1]), "spp": spp,
                "not_perspective": f"{s.id() or 0!r} ({s.class_name()})"}
    cam = Camera.from_mitsuba(s)
    up = -cam.camera_to_world[:3, 1]       # OpenCV y points down
    return {"fov": math.degrees(cam.fov_x), "resolution": (cam.width, cam.height), "up": _snap_axis(up), "spp": spp}


def _sensor_camera(sensor, i: int, p: Path, resolution) -> Camera:
    """Declared sensor ``i`` as a camera, resized to the width ``resolution[0]`` (aspect kept) when given."""
    if sensor.class_name() != "PerspectiveCamera":
        raise ValueError(f"{p}: sensor {i} ({sensor.id() or sensor.class_name()}) is not a 'perspective' camera")
    film = sensor.film()
    if tuple(film.crop_size()) != tuple(film.size()):
        raise ValueError(f"{p}: sensor {i} ({sensor.id()}) has a film crop window, which is not supported")
    c = Camera.from_mitsuba(sensor, name=f"sensor_{i:03d}")
    if not resolution:
        return c
    r = tuple(resolution)
    h = max(1, round(r[0] * c.height / c.width))
    if len(r) > 2 or (len(r) == 2 and abs(r[1] - h) > 1):
        raise ValueError(f"{p}: the scene's sensors keep their aspect ratio: give only a width "
                         f"(--resolution {r[0]} gives {r[0]}x{h})")
    return c.scaled(r[0], h)


def _declared_views(scene, p: Path, cfg: SceneConfig, test_every: int, spp: int) -> SceneViews:
    sensors = list(scene.sensors())
    if len(sensors) < 2:
        raise ValueError(f"{p}: rig 'sensors' needs a scene that declares several sensors (it has {len(sensors)})")
    cams = [_sensor_camera(s, i, p, cfg.resolution) for i, s in enumerate(sensors)]
    if test_every <= 0:
        return SceneViews(cams, [], spp, "sensors")
    return SceneViews([c for i, c in enumerate(cams) if i % test_every != 0],
                      [c for i, c in enumerate(cams) if i % test_every == 0], spp, "sensors")


# ---------------------------------------------------------------------------------------------------- generated rig
def _rig_film_size(cfg: SceneConfig, defaults: dict) -> tuple[int, int]:
    dw, dh = defaults.get("resolution") or FALLBACK_RESOLUTION
    res = tuple(cfg.resolution) if cfg.resolution else (dw, dh)
    if len(res) == 1:   # a width: the height keeps the sensor's aspect ratio
        res = (res[0], max(1, round(res[0] * dh / dw)))
    if len(res) != 2:
        raise ValueError(f"resolution takes a width or a width and a height, got {cfg.resolution}")
    width, height = int(res[0]), int(res[1])
    if width < 1 or height < 1:
        raise ValueError(f"resolution must be positive, got {width}x{height}")
    return width, height


def _rig_fov(cfg: SceneConfig, defaults: dict) -> float:
    fov = cfg.fov or defaults.get("fov") or FALLBACK_FOV
    if not 0.0 < fov < 180.0:
        raise ValueError(f"field of view must be in (0, 180) degrees, got {fov}")
    return fov


def _rig_up(cfg: SceneConfig, defaults: dict) -> np.ndarray:
    up = np.asarray(cfg.up if cfg.up is not None else defaults.get("up", FALLBACK_UP), dtype=np.float64)
    if up.shape != (3,) or not np.all(np.isfinite(up)) or np.linalg.norm(up) == 0:
        raise ValueError(f"up must be a non-zero 3-vector, got {cfg.up}")
    return up


def _rig_radius(cfg: SceneConfig, lo: np.ndarray, hi: np.ndarray, fov: float, width: int, height: int) -> float:
    """``cfg.radius``, or the distance at which the bounding sphere fills the narrower field of view."""
    radius = cfg.radius
    if radius is None:
        fov_min = min(math.radians(fov), 2.0 * math.atan(math.tan(math.radians(fov) / 2.0) * height / width))
        radius = 0.5 * float(np.linalg.norm(hi - lo)) / math.sin(fov_min / 2.0)
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"rig radius must be positive, got {radius}")
    return radius


def _generated_views(scene, p: Path, rig: str, cfg: SceneConfig, defaults: dict, spp: int, seed: int) -> SceneViews:
    if "not_perspective" in defaults and cfg.fov is None:
        # the rig's cameras are perspective: silently putting a 40-degree rig in place of an orthographic view would
        # train on pictures the scene's author never framed
        raise ValueError(f"{p}: the scene's sensor {defaults['not_perspective']} is not perspective, and the "
                         "generated camera rig is; give --fov DEGREES to train on a perspective rig anyway (the "
                         "rasterizer renders pinhole cameras only)")
    if cfg.views < 1 or cfg.test_views < 0:
        raise ValueError(f"the rig needs views >= 1 and test_views >= 0, got {cfg.views} and {cfg.test_views}")
    width, height = _rig_film_size(cfg, defaults)
    fov = _rig_fov(cfg, defaults)
    up = _rig_up(cfg, defaults)
    lo, hi = scene_bbox(scene)
    center = 0.5 * (lo + hi)
    radius = _rig_radius(cfg, lo, hi, fov, width, height)
    offsets = np.random.default_rng(seed).random(2) * 2.0 * math.pi

    def ring(n, offset, prefix):
        dirs = rig_directions(n, rig, up, cfg.elevation, offset)
        return [look_at_camera(center + radius * d, center, up, width, height, fov, f"{prefix}_{i:03d}")
                for i, d in enumerate(dirs)]

    return SceneViews(ring(cfg.views, offsets[0], "train"), ring(cfg.test_views, offsets[1], "test"), int(spp), rig)


def scene_views(scene, path: str | os.PathLike, cfg: SceneConfig, test_every: int = DataConfig().test_every,
                seed: int = 0) -> SceneViews:
    """Training and held-out cameras for ``scene`` (see the module docstring)."""
    if cfg.rig not in RIGS:
        raise ValueError(f"unknown camera rig {cfg.rig!r} (expected one of {', '.join(RIGS)})")
    defaults = _sensor_defaults(scene)
    spp = cfg.spp or defaults.get("spp") or FALLBACK_SPP
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    rig = cfg.rig
    if rig == "auto":
        rig = "sensors" if len(scene.sensors()) >= 2 else "hemisphere"
    if rig == "sensors":
        return _declared_views(scene, Path(path), cfg, test_every, spp)
    return _generated_views(scene, Path(path), rig, cfg, defaults, spp, seed)
