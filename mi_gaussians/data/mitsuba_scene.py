"""A Mitsuba scene file as a training dataset: cameras, path-traced references (cached), initial points.

``load_scene_dataset(scene.xml, cfg, cache_root)`` returns a :class:`~mi_gaussians.data.dataset.Dataset` like the
folder layouts do, so the trainer, ``mi-gs eval`` and the reports treat both alike:

- **Views.** A scene that declares several sensors is used as it is: its sensors are the cameras, every
  ``test_every``-th one (index % test_every == 0, as the COLMAP split) held out. Otherwise a seeded rig is generated
  around the scene's bounding box: ``views`` training and ``test_views`` held-out cameras on a hemisphere (elevation
  range above the plane orthogonal to ``up``) or a full sphere, each set spread evenly (a Fibonacci lattice with its own
  random azimuth offset, so test cameras are new poses), all looking at the centre of the bounding box. The rig takes
  the field of view, film size, up direction and sample count of the scene's first sensor unless told otherwise.
- **References** are rendered with the scene's own integrator (``mi.render``; a box pixel filter and an RGBA film, so
  alpha marks coverage) and cached as linear RGBA EXR files in ``cache_root/<key>/``, ``key`` hashing the scene file,
  every file it references, the cameras, the sample count and the Mitsuba version. Each file is written atomically as
  soon as it is rendered, so an interrupted run re-renders only what is missing, and a re-run renders nothing.
- **Colour.** Path-traced references are linear HDR radiance (values above 1 are legitimate). By default training sees
  them sRGB-encoded (the transfer curve continued above 1, nothing clipped): the loss then weighs errors the way they
  look, as for photographs, and dark regions are not drowned by highlights; the dataset's ``color_space`` is 'srgb',
  and renders are decoded back to linear for EXR outputs. ``linear=True`` trains on radiance itself.
- **Initial points**: see :mod:`mi_gaussians.data.scene_init`.

Problems with the scene file (missing, XML syntax error, a referenced file missing, no shapes, a sensor that is not a
pinhole camera) raise ``ValueError`` with one line naming the file.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..config import DataConfig, SceneConfig
from ..imwrite import linear_to_srgb, srgb_to_linear, write_exr
from ..io_utils import atomic_write_text
from .camera import Camera
from .images import ImageLoader

RIGS = ("auto", "sensors", "hemisphere", "sphere")
CACHE_VERSION = 1       # bump when how references are rendered changes (sampler, seeds, filter, clip planes)
FALLBACK_RESOLUTION = (256, 256)
FALLBACK_FOV = 40.0
FALLBACK_SPP = 128
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


# ---------------------------------------------------------------------------------------------------- loading
def parse_defines(defines) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` (Mitsuba's ``-D KEY=VALUE``) -> ``{KEY: VALUE}``."""
    out = {}
    for d in defines or ():
        key, sep, value = str(d).partition("=")
        if not sep or not key.strip() or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key.strip()):
            raise ValueError(f"scene parameter {d!r}: expected KEY=VALUE (as Mitsuba's -D KEY=VALUE)")
        out[key.strip()] = value
    return out


def load_file(path: str | os.PathLike, defines=()):
    """``mi.load_file`` with one-line errors naming the file (Mitsuba's "[parser.cpp:...]" prefix removed).

    ``defines``: ``"KEY=VALUE"`` strings that set the scene's ``<default name="KEY" .../>`` parameters."""
    import mitsuba as mi

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: scene file not found")
    params = parse_defines(defines)
    try:
        return mi.load_file(str(p), **params)
    except RuntimeError as e:   # Mitsuba: "[parser.cpp:1087] Parsing of XML file ... failed: ..." and friends
        msg = re.sub(r"^\[[^\]]*\]\s*", "", str(e).strip().splitlines()[0] if str(e).strip() else "cannot load")
        raise ValueError(f"{p}: {msg}") from None


def load_scene(path: str | os.PathLike, defines=()):
    """:func:`load_file` for fitting: the scene must also have at least one shape and a finite bounding box."""
    p = Path(path)
    scene = load_file(p, defines)
    if not scene.shapes():
        raise ValueError(f"{p}: the scene has no shapes (nothing to fit Gaussians to)")
    bbox = scene.bbox()
    lo, hi = np.array(bbox.min, dtype=np.float64), np.array(bbox.max, dtype=np.float64)
    if not (bbox.valid() and np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"{p}: the scene's bounding box is empty or infinite")
    return scene


def scene_bbox(scene) -> tuple[np.ndarray, np.ndarray]:
    b = scene.bbox()
    return np.array(b.min, dtype=np.float64), np.array(b.max, dtype=np.float64)


def referenced_files(path: str | os.PathLike, defines=()) -> list[Path]:
    """Files a scene file names with ``<string name="filename" .../>`` (and ``<include filename=...>``) that exist,
    recursively through included files; sorted, without duplicates. ``$KEY`` parameters are replaced by ``defines``
    or else the scene's ``<default>`` values, and relative names are resolved as Mitsuba's file resolver does: against
    the top scene's folder first, then against the folder of the file that names them."""
    top = Path(path).resolve()
    params = parse_defines(defines)
    seen: set[Path] = set()

    def substitute(value: str, defaults: dict) -> str:
        return re.sub(r"\$([A-Za-z_][A-Za-z0-9_]*)", lambda m: params.get(m.group(1), defaults.get(m.group(1),
                                                                                                   m.group(0))), value)

    def walk(xml: Path):
        try:
            root = ET.parse(xml).getroot()
        except (ET.ParseError, OSError):
            return
        defaults = {el.get("name"): el.get("value", "") for el in root.iter("default")}
        for el in root.iter():
            value = None
            if el.tag == "string" and el.get("name") == "filename":
                value = el.get("value")
            elif el.tag == "include":
                value = el.get("filename")
            if not value:
                continue
            value = substitute(value, defaults)
            for base in (top.parent, xml.parent):
                f = (base / value).resolve()
                if f.is_file():
                    break
            if f.is_file() and f not in seen:
                seen.add(f)
                if f.suffix.lower() == ".xml":
                    walk(f)

    walk(top)
    return sorted(seen)


# ---------------------------------------------------------------------------------------------------- cameras
def _snap_axis(v: np.ndarray) -> np.ndarray:
    k = int(np.argmax(np.abs(v)))
    out = np.zeros(3)
    out[k] = math.copysign(1.0, v[k])
    return out


def look_at_camera(origin, target, up, width: int, height: int, fov_x_deg: float, name: str) -> Camera:
    """A pinhole camera at ``origin`` looking at ``target`` (OpenCV axes: x right, y down, z forward)."""
    o, t, u = (np.asarray(a, dtype=np.float64).reshape(3) for a in (origin, target, up))
    f = t - o
    f /= np.linalg.norm(f)
    r = np.cross(f, u)
    if np.linalg.norm(r) < 1e-9:
        raise ValueError(f"camera {name!r}: the viewing direction is parallel to the up vector")
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = r, d, f, o
    fx = width / (2.0 * math.tan(math.radians(fov_x_deg) / 2.0))
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


@dataclass(frozen=True)
class SceneViews:
    """The cameras of a scene dataset and how the references are rendered."""

    train: list[Camera]
    test: list[Camera]
    spp: int
    source: str          # 'sensors' or 'hemisphere' / 'sphere' (generated)


def _sensor_defaults(scene) -> dict:
    """fov / resolution / up / spp of the scene's first perspective sensor (empty when it has none)."""
    for s in scene.sensors():
        if s.class_name() != "PerspectiveCamera":
            continue
        cam = Camera.from_mitsuba(s)
        up = -cam.camera_to_world[:3, 1]       # OpenCV y points down
        spp = int(s.sampler().sample_count()) if s.sampler() is not None else None
        return {"fov": math.degrees(cam.fov_x), "resolution": (cam.width, cam.height), "up": _snap_axis(up),
                "spp": spp}
    return {}


def scene_views(scene, path: str | os.PathLike, cfg: SceneConfig, test_every: int = DataConfig().test_every,
                seed: int = 0) -> SceneViews:
    """Training and held-out cameras for ``scene`` (see the module docstring)."""
    p = Path(path)
    if cfg.rig not in RIGS:
        raise ValueError(f"unknown camera rig {cfg.rig!r} (expected one of {', '.join(RIGS)})")
    sensors = list(scene.sensors())
    defaults = _sensor_defaults(scene)
    spp = cfg.spp or defaults.get("spp") or FALLBACK_SPP
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    rig = cfg.rig
    if rig == "auto":
        rig = "sensors" if len(sensors) >= 2 else "hemisphere"
    if rig == "sensors":
        if len(sensors) < 2:
            raise ValueError(f"{p}: rig 'sensors' needs a scene that declares several sensors (it has {len(sensors)})")
        cams = []
        for i, s in enumerate(sensors):
            if s.class_name() != "PerspectiveCamera":
                raise ValueError(f"{p}: sensor {i} ({s.id() or s.class_name()}) is not a 'perspective' camera")
            film = s.film()
            if tuple(film.crop_size()) != tuple(film.size()):
                raise ValueError(f"{p}: sensor {i} ({s.id()}) has a film crop window, which is not supported")
            c = Camera.from_mitsuba(s, name=f"sensor_{i:03d}")
            if cfg.resolution:
                r = tuple(cfg.resolution)
                h = max(1, round(r[0] * c.height / c.width))
                if len(r) > 2 or (len(r) == 2 and abs(r[1] - h) > 1):
                    raise ValueError(f"{p}: the scene's sensors keep their aspect ratio: give only a width "
                                     f"(--resolution {r[0]} gives {r[0]}x{h})")
                c = c.scaled(r[0], h)
            cams.append(c)
        if test_every <= 0:
            return SceneViews(cams, [], spp, "sensors")
        return SceneViews([c for i, c in enumerate(cams) if i % test_every != 0],
                          [c for i, c in enumerate(cams) if i % test_every == 0], spp, "sensors")

    if cfg.views < 1 or cfg.test_views < 0:
        raise ValueError(f"the rig needs views >= 1 and test_views >= 0, got {cfg.views} and {cfg.test_views}")
    dw, dh = defaults.get("resolution") or FALLBACK_RESOLUTION
    res = tuple(cfg.resolution) if cfg.resolution else (dw, dh)
    if len(res) == 1:   # a width: the height keeps the sensor's aspect ratio
        res = (res[0], max(1, round(res[0] * dh / dw)))
    if len(res) != 2:
        raise ValueError(f"resolution takes a width or a width and a height, got {cfg.resolution}")
    width, height = int(res[0]), int(res[1])
    if width < 1 or height < 1:
        raise ValueError(f"resolution must be positive, got {width}x{height}")
    fov = cfg.fov or defaults.get("fov") or FALLBACK_FOV
    if not 0.0 < fov < 180.0:
        raise ValueError(f"field of view must be in (0, 180) degrees, got {fov}")
    up = np.asarray(cfg.up if cfg.up is not None else defaults.get("up", (0.0, 1.0, 0.0)), dtype=np.float64)
    if up.shape != (3,) or not np.all(np.isfinite(up)) or np.linalg.norm(up) == 0:
        raise ValueError(f"up must be a non-zero 3-vector, got {cfg.up}")
    lo, hi = scene_bbox(scene)
    center = 0.5 * (lo + hi)
    radius = cfg.radius
    if radius is None:
        fov_min = min(math.radians(fov), 2.0 * math.atan(math.tan(math.radians(fov) / 2.0) * height / width))
        radius = 0.5 * float(np.linalg.norm(hi - lo)) / math.sin(fov_min / 2.0)
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"rig radius must be positive, got {radius}")
    rng = np.random.default_rng(seed)
    offsets = rng.random(2) * 2.0 * math.pi

    def ring(n, offset, prefix):
        dirs = rig_directions(n, rig, up, cfg.elevation, offset)
        return [look_at_camera(center + radius * d, center, up, width, height, fov, f"{prefix}_{i:03d}")
                for i, d in enumerate(dirs)]

    return SceneViews(ring(cfg.views, offsets[0], "train"), ring(cfg.test_views, offsets[1], "test"), int(spp), rig)


# ---------------------------------------------------------------------------------------------------- references
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


def _multijitter_count(spp: int) -> int:
    """The sample count Mitsuba's multijitter sampler uses for ``spp`` (it rounds up to a w x h grid)."""
    w = math.ceil(math.sqrt(spp))
    return w * math.ceil(spp / w)


def render_reference(scene, cam: Camera, spp: int, seed: int) -> np.ndarray:
    """One path-traced reference: (H, W, 4) float32 linear RGB + alpha (box filter), with the scene's integrator.

    The clip planes follow the scene's size: near 1e-4 and far 10 times the farthest bounding-box corner."""
    import mitsuba as mi

    lo, hi = scene_bbox(scene)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    far = 10.0 * float(np.linalg.norm(corners - cam.center, axis=1).max())
    diag = float(np.linalg.norm(hi - lo))
    d = cam.to_mitsuba(near_clip=max(1e-4 * diag, 1e-7), far_clip=max(far, 1e-3))
    d["sampler"] = {"type": "multijitter", "sample_count": _multijitter_count(spp)}
    sensor = mi.load_dict(d)
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


def render_references(scene, views: SceneViews, cache_dir: Path, progress: bool = True,
                      log: Callable[[str], None] | None = None) -> dict[str, Path]:
    """Render every camera that has no EXR in ``cache_dir`` yet; returns camera name -> EXR path."""
    from tqdm import tqdm

    cams = [("train", i, c) for i, c in enumerate(views.train)] + [("test", i, c) for i, c in enumerate(views.test)]
    paths = {c.name: cache_dir / split / f"{c.name}.exr" for split, _, c in cams}
    todo = [(split, i, c) for split, i, c in cams if not paths[c.name].is_file()]
    if todo and log is not None:
        log(f"rendering {len(todo)} of {len(cams)} references at {views.spp} spp -> {cache_dir}")
    elif log is not None:
        log(f"reusing the {len(cams)} cached references in {cache_dir}")
    for split, i, c in tqdm(todo, desc="references", unit="view", disable=not progress or not todo):
        seed = i if split == "train" else 1_000_003 + i
        write_exr(paths[c.name], render_reference(scene, c, views.spp, seed))
    return paths


class EncodedLoader:
    """An :class:`ImageLoader` whose RGB is sRGB-encoded after compositing (HDR values above 1 are kept)."""

    def __init__(self, base: ImageLoader):
        self.base = base

    def load(self, path):
        rgb, alpha = self.base.load(path)
        return np.ascontiguousarray(linear_to_srgb(np.maximum(rgb, 0.0))), alpha


# ---------------------------------------------------------------------------------------------------- dataset
def load_scene_dataset(path: str | os.PathLike, cfg: SceneConfig = SceneConfig(), cache_root: str | os.PathLike = ".",
                       background=(0.0, 0.0, 0.0), test_every: int = DataConfig().test_every, seed: int = 0,
                       progress: bool = True, log: Callable[[str], None] | None = None, expect_key: str | None = None):
    """Load ``path``, make its cameras, render (or reuse) the references, initialize points: a ``Dataset``.

    ``expect_key``: the references key of an earlier run (``--resume``, ``mi-gs eval``); a scene that no longer
    gives it is refused before anything is rendered."""
    from . import scene_init
    from .dataset import Dataset, View

    p = Path(path)
    scene = load_scene(p, cfg.defines)
    views = scene_views(scene, p, cfg, test_every=test_every, seed=seed)
    key = cache_key(p, views, cfg.defines)
    if expect_key is not None and key != expect_key:
        raise ValueError(f"{p}: the scene, a file it references or its parameters changed since the run's references "
                         f"were rendered (key {key}, the run's {expect_key}); start a new run")
    cache_dir = Path(cache_root) / key
    rig_file = cache_dir / "rig.json"
    if not rig_file.is_file():
        rig = {"scene": str(p.resolve()), "defines": list(cfg.defines), "key": key, "source": views.source, "spp": views.spp,
               "train": [c.to_dict() for c in views.train], "test": [c.to_dict() for c in views.test]}
        cache_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(rig_file, json.dumps(rig, indent=1) + "\n")
    paths = render_references(scene, views, cache_dir, progress=progress, log=log)
    # ``background`` is in the training colour space (what the Gaussians are drawn over): the references (linear,
    # premultiplied alpha) are composited over its linear value, so that encoded targets show ``background`` itself
    bg = tuple(float(b) for b in np.asarray(background, dtype=np.float64).reshape(3))
    bg_linear = bg if cfg.linear else tuple(float(b) for b in srgb_to_linear(np.asarray(bg, np.float32)))

    def view(c: Camera):
        loader = ImageLoader((c.width, c.height), (c.width, c.height), bg_linear)
        return View(c.name, c, paths[c.name], loader if cfg.linear else EncodedLoader(loader))

    train, test = [view(c) for c in views.train], [view(c) for c in views.test]
    # (SfM runs on the composited training images: its cache depends on the background and the colour space)
    sfm_tag = "_".join(f"{b:.4g}" for b in bg) + ("_linear" if cfg.linear else "")
    xyz, rgb = scene_init.initial_points(scene, cfg.init, cfg.init_points, train, cache_dir / f"sfm_{sfm_tag}",
                                         seed=seed, linear=cfg.linear, log=log)
    return Dataset(root=p, layout="mitsuba", train=train, test=test, points_xyz=xyz, points_rgb=rgb,
                   background=np.asarray(bg, dtype=np.float32), color_space="linear" if cfg.linear else "srgb",
                   references=cache_dir)


def write_gaussian_scene(path: str | os.PathLike, ply: str, cam: Camera, color_space: str = "linear",
                         background=(0.0, 0.0, 0.0)) -> None:
    """A Mitsuba scene file that renders the Gaussians of ``ply`` (a path relative to the scene file's folder) with
    the ``gaussian_splatting`` integrator from camera ``cam`` (written atomically)."""
    from .camera import MI_TO_CV

    m = cam.camera_to_world @ MI_TO_CV
    matrix = " ".join(f"{v:.9g}" for v in m.reshape(-1))
    bg = ", ".join(f"{float(b):.6g}" for b in np.asarray(background).reshape(3))
    text = f"""<!-- Gaussians fitted by mi-gs optimize, rendered by mi-gaussians' rasterizer inside Mitsuba:
         mi-gs render {Path(path).name} -o render.exr
     The camera is the held-out view {cam.name!r}. color_space="{color_space}": the Gaussians hold {"sRGB-encoded colours, decoded to linear radiance after blending" if color_space == "srgb" else "linear radiance"}.
     Mitsuba's own ray tracer for ellipsoids: -Dintegrator=volprim_rf_basic (it knows no color_space). -->
<scene version="3.0.0">
    <default name="integrator" value="gaussian_splatting"/>

    <integrator type="$integrator">
        <string name="color_space" value="{color_space}"/>
        <rgb name="background" value="{bg}"/>
    </integrator>

    <sensor type="perspective" id="camera">
        <string name="fov_axis" value="x"/>
        <float name="fov" value="{math.degrees(cam.fov_x):.9g}"/>
        <float name="principal_point_offset_x" value="{(cam.width / 2.0 - cam.cx) / cam.width:.9g}"/>
        <float name="principal_point_offset_y" value="{(cam.height / 2.0 - cam.cy) / cam.height:.9g}"/>
        <transform name="to_world">
            <matrix value="{matrix}"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="{cam.width}"/>
            <integer name="height" value="{cam.height}"/>
            <string name="pixel_format" value="rgba"/>
            <rfilter type="box"/>
        </film>
    </sensor>

    <shape type="ellipsoids" id="gaussians">
        <string name="filename" value="{ply}"/>
    </shape>
</scene>
"""
    atomic_write_text(Path(path), text)
