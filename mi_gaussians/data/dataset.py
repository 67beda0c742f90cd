"""Datasets: detect the layout of a scene folder, validate it completely, and describe its views.

Layouts (checked in this order, like the reference 3DGS):

- ``colmap``: ``images/`` + ``sparse/0`` (or ``sparse/``) with ``cameras``, ``images``, ``points3D`` as .bin or .txt.
  Test split: images sorted by name, ``index % test_every == 0`` is test. Initial points: the SfM points (random
  points around the cameras, as for ngp, when the model has none).
  With ``resolution = r > 1`` and an ``images_r/`` folder, its images are read instead of resampling ``images/``
  (the same for the ``blender`` and ``ngp`` layouts: ``images_r/`` beside the transforms file, nerfstudio's
  downscaled folders, holding each frame's image at its relative path without a leading ``images/``).
  Masks (``masks=True``): when a ``masks/`` folder (``masks_r/`` with ``images_r/``) sits beside ``images/``, every
  image needs its mask there, named like the image, the image name + ``.png`` (COLMAP's convention) or
  ``<stem>_mask.<ext>``; white is the object. The image is composited through it over the background and the mask is
  the view's alpha (so a random background trains the masked-out pixels as background), as for turntable captures
  whose static background contradicts the object-centred poses. A mask has the image file's size or the camera's.
- ``blender``: ``transforms_train.json`` + ``transforms_test.json`` (NeRF-synthetic). The files define the split
  (``transforms_val.json`` is ignored, as in the reference); ``test_every = 0`` merges the test views into train,
  as the reference does without ``--eval``. Initial points: random in ``[-1.3, 1.3]^3`` (see ``pointcloud.py``).
- ``ngp``: one ``transforms.json`` (instant-ngp / nerfstudio). Frames whose image file is missing are skipped with a
  logged warning (instant-ngp's own fox scene lists 17 such frames); the split is the COLMAP one over the remaining
  frames. Initial points: random in a cube around the cameras' focus point (see ``pointcloud.py``).

Every view's camera is a pinhole :class:`Camera` for the image ``View.load_image`` returns: distorted cameras (COLMAP
SIMPLE_RADIAL/RADIAL/OPENCV/FULL_OPENCV, OpenCV coefficients in transforms files) are undistorted in memory the way
COLMAP's image undistorter does it. Resolution ``r`` gives images of ``round(W / r) x round(H / r)`` (as the reference's
``-r``), area-averaged; intrinsics are scaled per axis.

Loading validates everything that can be checked without decoding pixels (layout, files, JSON, camera models, poses,
image sizes from the headers) and raises ``ValueError`` with one line naming the file. It writes nothing.
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import DataConfig
from ..conventions import MIN_IMAGE_SIDE
from . import blender as _blender
from . import colmap as _colmap
from . import pointcloud as _pc
from .camera import GL_TO_CV, Camera
from .images import IMAGE_EXTENSIONS, ImageLoader, Undistorter, color_space_of, image_size, resolve_image_file

log = logging.getLogger(__name__)

_DEFAULTS = DataConfig()


@dataclass(frozen=True)
class View:
    """One image and its camera. ``camera`` already matches the loaded image (resolution, undistortion)."""

    name: str
    camera: Camera
    image_path: Path
    loader: ImageLoader = field(repr=False, compare=False)
    depth_path: Path | None = None       # Mitsuba scenes: the exact depth (see ``scene_references.py``)

    def load_image(self) -> np.ndarray:
        """The image as (H, W, 3) float32 (H, W = camera.height, camera.width), RGBA composited over the background.

        Values are those of the file (see ``Dataset.color_space``). Decoded on every call (nothing is cached)."""
        return self.loader.load(self.image_path)[0]

    def load_depth(self) -> np.ndarray | None:
        """The exact view-space depth, (H, W) float32, +inf where nothing is hit; None when the dataset has none."""
        if self.depth_path is None:
            return None
        d = np.load(self.depth_path)
        if d.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"{self.depth_path}: depth of shape {d.shape}, the view is "
                             f"{self.camera.height}x{self.camera.width}")
        return d.astype(np.float32)

    def load_alpha(self) -> np.ndarray:
        """The alpha channel as (H, W) float32 in [0, 1], resampled like the image; ones when the file has none."""
        a = self.loader.load(self.image_path)[1]
        return np.ones((self.camera.height, self.camera.width), np.float32) if a is None else a


@dataclass(frozen=True)
class Dataset:
    """A loaded scene: train/test views, initial points, background, and the colour encoding of the images."""

    root: Path
    layout: str                          # 'colmap' | 'blender' | 'ngp' | 'mitsuba' (a scene file: scene_dataset.py)
    train: list[View]
    test: list[View]
    points_xyz: np.ndarray | None = field(repr=False)   # (M, 3) float32
    points_rgb: np.ndarray | None = field(repr=False)   # (M, 3) float32 in [0, 1]
    background: np.ndarray = field(repr=False)          # (3,) float32
    color_space: str = "srgb"            # 'srgb' (PNG/JPEG values / 255, not linearized) or 'linear' (EXR)
    resolution: int = 1
    references: Path | None = None       # Mitsuba scenes: the folder of the cached reference renders
    points_from: str = "layout"          # where points_xyz came from: 'layout' (the dataset's own, e.g. COLMAP's
                                         # points3D), a random sampler ('cube', 'frustum'), 'triangulated', 'none'...

    @property
    def views(self) -> list[View]:
        """Train views followed by test views."""
        return list(self.train) + list(self.test)

    @property
    def center(self) -> np.ndarray:
        """Mean of the train camera centres, (3,) float64."""
        return _pc.camera_extent(np.stack([v.camera.center for v in self.train]))[0]

    @property
    def extent(self) -> float:
        """The rig's extent: 1.1 * max distance of the train camera centres from their mean (3DGS ``getNerfppNorm``)."""
        return _pc.camera_extent(np.stack([v.camera.center for v in self.train]))[1]

    def scene_extent(self, rule: str = DataConfig.extent) -> float:
        """The length scale a run trains with (``data.extent``; :func:`.pointcloud.scene_extent` of the train
        cameras and ``points_xyz``); :class:`.pointcloud.DegenerateScale` naming the dataset when it is 0 or not
        finite."""
        return self.scene_scale(rule)[0]

    def scene_scale(self, rule: str = DataConfig.extent) -> tuple[float, str | None]:
        """(:meth:`scene_extent`, why it fell back to the cameras' spread or None): :func:`.pointcloud.scene_scale`."""
        try:
            return _pc.scene_scale([v.camera for v in self.train], self.points_xyz, rule)
        except _pc.DegenerateScale as e:
            raise _pc.DegenerateScale(f"{self.root}: {e}") from None


# ---------------------------------------------------------------------------------------------------- detection
def detect_layout(path: str | os.PathLike) -> str:
    """'colmap', 'blender' or 'ngp' for a scene folder; ``ValueError`` for anything else."""
    root = Path(path)
    if not root.exists():
        raise ValueError(f"{root}: dataset folder not found")
    if not root.is_dir():
        raise ValueError(f"{root}: not a folder (give the scene folder)")
    if _colmap.find_model_dir(root) is not None:
        return "colmap"
    if (root / "transforms_train.json").is_file():
        return "blender"
    if (root / "transforms.json").is_file():
        return "ngp"
    if not any(root.iterdir()):
        raise ValueError(f"{root}: empty folder, not a dataset")
    raise ValueError(f"{root}: unknown dataset layout (expected images/ + sparse/0/ for COLMAP, "
                     "transforms_train.json + transforms_test.json for Blender, or transforms.json for instant-ngp)")


# ---------------------------------------------------------------------------------------------------- helpers
def _reduced(n: int, r: int) -> int:
    return max(1, int(round(n / r)))


def _check_options(resolution, background, test_every, random_points, seed) -> np.ndarray:
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 1:
        raise ValueError(f"resolution must be a positive integer divisor (1, 2, 4, 8, ...), got {resolution!r}")
    if isinstance(test_every, bool) or not isinstance(test_every, (int, np.integer)) or test_every < 0:
        raise ValueError(f"test_every must be an integer >= 0 (0: no test split), got {test_every!r}")
    if isinstance(random_points, bool) or not isinstance(random_points, (int, np.integer)) or random_points < 0:
        raise ValueError(f"random_points must be an integer >= 0, got {random_points!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    try:
        bg = np.asarray(background, dtype=np.float32).reshape(3)
    except (TypeError, ValueError):
        raise ValueError(f"background must be three numbers (r, g, b), got {background!r}") from None
    if not np.all(np.isfinite(bg)):
        raise ValueError(f"background must be finite, got {background!r}")
    return bg


class _Builder:
    """Turns (image file, full-resolution camera) pairs into Views for one resolution and background."""

    def __init__(self, resolution: int, background: np.ndarray):
        self.resolution = resolution
        self.bg = tuple(float(b) for b in background)
        self._undistorters: dict[tuple, Undistorter] = {}

    def undistorter(self, model: str, width: int, height: int, params: tuple, source: str) -> Undistorter:
        key = (model, width, height, tuple(params))
        u = self._undistorters.get(key)
        if u is None:
            u = self._undistorters[key] = Undistorter(model, width, height, params, source)
        return u

    def view(self, name: str, image_path: Path, file_size: tuple[int, int], full_size: tuple[int, int],
             w2c: np.ndarray, pinhole: tuple[float, float, float, float] | None,
             undistorter: Undistorter | None, source: str, reduced_file: bool = False,
             mask_path: Path | None = None) -> View:
        """``full_size``/``pinhole``: the camera's own size and (fx, fy, cx, cy) (ignored with an undistorter).
        ``file_size``: the image file's (w, h) from its header. ``reduced_file``: the file is already reduced by r
        (an ``images_r`` folder), so its size may differ from round(W / r) by one pixel (other tools round
        differently) and the camera follows the file."""
        r = self.resolution
        W, H = full_size
        fw, fh = file_size
        if reduced_file:
            ew, eh = W / r, H / r
            if abs(fw - ew) > 1.0 or abs(fh - eh) > 1.0:
                raise ValueError(f"{image_path}: image is {fw}x{fh}, but {source} says {W}x{H}, i.e. about "
                                 f"{_reduced(W, r)}x{_reduced(H, r)} at resolution 1/{r}")
            src = (fw, fh)
        else:
            if (fw, fh) != (W, H):
                raise ValueError(f"{image_path}: image is {fw}x{fh}, but {source} says {W}x{H}")
            src = (_reduced(W, r), _reduced(H, r))
        try:
            if undistorter is None:
                fx, fy, cx, cy = pinhole
                cam = Camera(W, H, fx, fy, cx, cy, w2c, name).scaled(*src)
                out = src
            else:
                pw, ph, fx, fy, cx, cy = undistorter.pinhole
                out = (src if (pw, ph) == (W, H) else (_reduced(pw, r), _reduced(ph, r)))
                cam = Camera(pw, ph, fx, fy, cx, cy, w2c, name).scaled(*out)
        except ValueError as e:
            raise ValueError(f"{source}: {e}") from None
        return View(name, cam, image_path, ImageLoader(out, src, self.bg, undistorter, mask_path))


def _split_by_index(views: list[View], test_every: int) -> tuple[list[View], list[View]]:
    views = sorted(views, key=lambda v: v.name)
    if test_every == 0:
        return views, []
    return ([v for i, v in enumerate(views) if i % test_every != 0],
            [v for i, v in enumerate(views) if i % test_every == 0])


# ---------------------------------------------------------------------------------------------------- COLMAP
def _masks_dir(root: Path, reduced: int) -> Path | None:
    """The mask folder beside the image folder: masks_r/ for images_r/ (when present), else masks/, else None."""
    for d in ([root / f"masks_{reduced}"] if reduced > 1 else []) + [root / "masks"]:
        if d.is_dir():
            return d
    return None


def _mask_file(masks_dir: Path, image: Path, name: str, file_size: tuple[int, int],
               full_size: tuple[int, int]) -> Path:
    """The mask of image ``name`` (a path relative to the image folder), with its size checked from its header."""
    stem = Path(name)
    candidates = [masks_dir / name, masks_dir / (name + ".png")]
    candidates += [masks_dir / stem.with_name(stem.stem + suffix + ext) for suffix in ("", "_mask")
                   for ext in (stem.suffix,) + IMAGE_EXTENSIONS]
    mask = next((c for c in candidates if c.is_file()), None)
    if mask is None:
        raise ValueError(f"{masks_dir / name}: no mask for {image} (a masks folder needs one mask per image: "
                         f"{name}, {name}.png or {stem.stem}_mask{stem.suffix})")
    size = image_size(mask)
    if size not in (file_size, full_size):
        raise ValueError(f"{mask}: mask is {size[0]}x{size[1]}, but its image {image} is "
                         f"{file_size[0]}x{file_size[1]}")
    return mask


def _load_colmap(root: Path, builder: _Builder, test_every: int, n_points: int, seed: int, masks: bool,
                 random_init: str, own_points: bool):
    model_dir = _colmap.find_model_dir(root)
    model = _colmap.read_model(model_dir)
    images_dir = root / "images"
    reduced = builder.resolution > 1 and (root / f"images_{builder.resolution}").is_dir()
    if reduced:
        images_dir = root / f"images_{builder.resolution}"
    if not images_dir.is_dir():
        raise ValueError(f"{images_dir}: image folder not found (COLMAP layout: images/ next to sparse/)")
    masks_dir = _masks_dir(root, builder.resolution if reduced else 1) if masks else None
    if masks_dir is not None:
        log.info("%s: compositing every image through its mask over the background", masks_dir)
    cam_file = model.file("cameras")
    views = []
    for im in model.images:
        c = model.cameras[im.camera_id]
        path = images_dir / im.name
        if not path.is_file():
            raise ValueError(f"{path}: image file not found (listed in {model.file('images')})")
        undistorter = None
        if not c.is_pinhole:
            undistorter = builder.undistorter(c.model, c.width, c.height, c.params, f"{cam_file}: camera {c.camera_id}")
        file_size = image_size(path)
        mask = (None if masks_dir is None
                else _mask_file(masks_dir, path, im.name, file_size, (c.width, c.height)))
        views.append(builder.view(im.name, path, file_size, (c.width, c.height), im.world_to_camera,
                                  None if undistorter else c.pinhole_intrinsics(), undistorter,
                                  f"{cam_file} (camera {c.camera_id})", reduced_file=reduced, mask_path=mask))
    train, test = _split_by_index(views, test_every)
    if own_points and len(model.points_xyz):
        return train, test, model.points_xyz, model.points_rgb, True
    return (train, test) + _random_points(train, n_points, seed, random_init,
                                          lambda: _points_around(train, n_points, seed)) + (False,)


def _points_around(train: list[View], n_points: int, seed: int):
    """Random initial points in a cube around the focus point of the train cameras (see pointcloud.py)."""
    if n_points <= 0 or not train:
        return None, None
    centers = np.stack([v.camera.center for v in train])
    forward = np.stack([v.camera.world_to_camera[2, :3] for v in train])   # camera +z in world space
    return _pc.points_around_cameras(n_points, centers, forward, seed)


# ---------------------------------------------------------------------------------------------------- transforms
def _frame_views(path: Path, builder: _Builder, skip_missing: bool) -> list[View]:
    """The views of one transforms file. With resolution r > 1 and an ``images_r/`` folder beside the file, every
    frame's image is read from ``images_r/`` (nerfstudio's downscaled folders), already reduced, at its path relative
    to the file's folder without a leading ``images/``: ``images/0001.jpg`` -> ``images_4/0001.jpg``,
    ``train/r_0.png`` -> ``images_2/train/r_0.png`` (a Blender scene's train and test images share names)."""
    frames = _blender.read_frames(path)
    reduced_dir = path.parent / f"images_{builder.resolution}"
    reduced = builder.resolution > 1 and reduced_dir.is_dir()
    files = []                                      # (frame, image path, exists, file size) of the file to read
    for f in frames:
        if reduced:
            rel = Path(os.path.relpath(f.image_path, path.parent))
            rel = Path(*rel.parts[1:]) if len(rel.parts) > 1 and rel.parts[0] == "images" else rel
            if rel.parts and rel.parts[0] == "..":
                rel = Path(rel.name)                # (an image outside the scene's folder: by its name)
            image_path, exists = resolve_image_file(reduced_dir, rel.as_posix())
            files.append((f, image_path, exists, image_size(image_path) if exists else None))
        else:
            files.append((f, f.image_path, f.exists, f.file_size))
    missing = [(f, p) for f, p, exists, _ in files if not exists]
    if missing and not skip_missing:
        raise ValueError(f"{missing[0][1]}: image file not found (frame {missing[0][0].index} of {path})")
    if missing:
        names = ", ".join(f.name for f, _ in missing[:5]) + (", ..." if len(missing) > 5 else "")
        log.warning("%s: skipping %d of %d frames whose image file is missing (%s)", path, len(missing),
                    len(frames), names)
    views = []
    for f, image_path, exists, file_size in files:
        if not exists:
            continue
        intrinsics = f.intrinsics
        w2c = np.linalg.inv(f.camera_to_world_gl @ GL_TO_CV)
        source = f"{path} (frame {f.index})"
        undistorter = None
        if intrinsics.distortion is not None:
            model, params = intrinsics.distortion
            undistorter = builder.undistorter(model, intrinsics.width, intrinsics.height, params, source)
        views.append(builder.view(f.name, image_path, file_size, (intrinsics.width, intrinsics.height), w2c,
                                  (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy), undistorter, source,
                                  reduced_file=reduced))
    if not views:
        raise ValueError(f"{path}: none of the {len(frames)} frames has its image file")
    return views


def _random_points(train: list[View], n_points: int, seed: int, random_init: str, cube):
    """Initial points for a layout without SfM points: ``cube()`` (the reference's), or the frustum sampler."""
    if n_points <= 0 or not train:
        return None, None
    log.debug("initial points: %d random (%s)", n_points, random_init)
    if random_init == "frustum":
        return _pc.points_in_view(n_points, [v.camera for v in train], seed)
    return cube()


def _load_blender(root: Path, builder: _Builder, test_every: int, n_points: int, seed: int, random_init: str):
    train = _frame_views(root / "transforms_train.json", builder, skip_missing=False)   # file order, as the reference
    test_file = root / "transforms_test.json"
    if not test_file.is_file():
        raise ValueError(f"{test_file}: file not found (the Blender layout needs transforms_train.json and "
                         "transforms_test.json)")
    test = _frame_views(test_file, builder, skip_missing=False)
    if test_every == 0:
        train, test = train + test, []
    xyz, rgb = _random_points(train, n_points, seed, random_init, lambda: _pc.blender_random_points(n_points, seed))
    return train, test, xyz, rgb


def _load_ngp(root: Path, builder: _Builder, test_every: int, n_points: int, seed: int, random_init: str):
    views = _frame_views(root / "transforms.json", builder, skip_missing=True)
    train, test = _split_by_index(views, test_every)
    return (train, test) + _random_points(train, n_points, seed, random_init,
                                          lambda: _points_around(train, n_points, seed))


# ---------------------------------------------------------------------------------------------------- entry point
def load_dataset(path: str | os.PathLike, resolution: int = _DEFAULTS.resolution,
                 background=_DEFAULTS.background, test_every: int = _DEFAULTS.test_every,
                 random_points: int = _DEFAULTS.random_points, seed: int = _DEFAULTS.seed,
                 masks: bool = _DEFAULTS.masks, random_init: str = "cube", own_points: bool = True) -> Dataset:
    """Load and validate a scene folder (layout detected, see the module docstring). Lazy: no pixels are decoded.

    resolution: divide the image size by this (``round(W / r) x round(H / r)``); background: (3,) colour that RGBA
    images are composited over; test_every: hold-out period for COLMAP/ngp (0: all train; Blender: 0 merges test into
    train); random_points / seed: initial points for layouts without SfM points (0: none); masks: use a COLMAP
    scene's masks/ folder when there is one; random_init: the sampler of random points, 'cube' (the reference's) or
    'frustum' (see pointcloud.py; a run chooses by ``DataConfig.init``); own_points: start from the layout's own
    points (COLMAP's points3D) when it has them, else (False) from random ones as a layout without points does.
    Defaults are those of :class:`mi_gaussians.config.DataConfig`.
    """
    bg = _check_options(resolution, background, test_every, random_points, seed)
    if random_init not in _pc.RANDOM_INITS:
        raise ValueError(f"data.random_init must be one of {', '.join(_pc.RANDOM_INITS)}, got {random_init!r}")
    if not isinstance(masks, (bool, np.bool_)):
        raise ValueError(f"masks must be True or False, got {masks!r}")
    root = Path(path)
    layout = detect_layout(root)
    builder = _Builder(int(resolution), bg)
    own = False
    if layout == "colmap":
        train, test, xyz, rgb, own = _load_colmap(root, builder, int(test_every), int(random_points), int(seed),
                                                  bool(masks), random_init, bool(own_points))
    elif layout == "blender":
        train, test, xyz, rgb = _load_blender(root, builder, int(test_every), int(random_points), int(seed),
                                              random_init)
    else:
        train, test, xyz, rgb = _load_ngp(root, builder, int(test_every), int(random_points), int(seed), random_init)
    if not train:
        raise ValueError(f"{root}: no training views (test_every={test_every} leaves none)")
    spaces = {color_space_of(v.image_path) for v in train + test}
    if len(spaces) > 1:
        raise ValueError(f"{root}: mixed image encodings (EXR and PNG/JPEG) in one dataset")
    names = [v.name for v in train + test]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"{root}: image {dup!r} appears more than once")
    return Dataset(root=root, layout=layout, train=train, test=test, points_xyz=xyz, points_rgb=rgb,
                   background=bg, color_space=spaces.pop(), resolution=int(resolution),
                   points_from="layout" if own else (random_init if xyz is not None else "none"))


# ---------------------------------------------------------------------------------------------------- verification
def check_trainable_size(ds: Dataset) -> None:
    """Training images must have at least ``MIN_IMAGE_SIDE`` pixels per side (a resolution divisor too large for
    the images is refused, naming the first view too small)."""
    for v in ds.views:
        c = v.camera
        if min(c.width, c.height) < MIN_IMAGE_SIDE:
            raise ValueError(f"{v.image_path}: at resolution 1/{ds.resolution} this view is {c.width}x{c.height} "
                             f"pixels; training needs at least {MIN_IMAGE_SIDE} per side (use a smaller divisor)")


#: seconds before a progress bar shows (a short wait says nothing; a long one is never silent); the environment's
#: MI_GS_PROGRESS_DELAY replaces it (0: at once, as the tests ask on tiny data)
PROGRESS_DELAY = float(os.environ.get("MI_GS_PROGRESS_DELAY", "2") or 2)


def unreadable_images(views: list[View], progress: bool = False) -> list[str]:
    """Decode every view's image (and mask) once, with a progress bar on stderr (``progress``; after
    :data:`PROGRESS_DELAY` seconds); the one-line problems of those that cannot be read ("file: problem"), empty when
    all can. Run before anything is written, since views are otherwise decoded only when
    training or evaluation reaches them."""
    from tqdm import tqdm

    problems = []
    for v in tqdm(views, desc="checking images", unit="image", disable=not progress or len(views) < 2,
                  leave=False, delay=PROGRESS_DELAY, file=sys.stderr):
        try:
            v.loader.load(v.image_path)
        except (ValueError, OSError) as e:
            problems.append(str(e) if str(v.image_path) in str(e) else f"{v.image_path}: {e}")
    return problems


def verify_images(views: list[View], progress: bool = False) -> None:
    """:func:`unreadable_images`, raising ValueError with the first problem (and how many more there are)."""
    problems = unreadable_images(views, progress)
    if problems:
        more = f" (and {len(problems) - 1} more unreadable images)" if len(problems) > 1 else ""
        raise ValueError(problems[0] + more)


FINGERPRINT_VERSION = "v3"     # v3: initial points count only when they are the dataset's own


def fingerprint(ds: Dataset) -> str:
    """A content fingerprint of what a run trains on: every view's name, camera (and lens distortion) and image (and
    mask) file bytes, the dataset's own points (not random or triangulated ones: those follow from the rest and the
    settings), the background and the colour encoding (SHA-256, hex). A resumed run must see the same.

    Canonical, so that how a file is parsed cannot change it: poses and intrinsics rounded to 1e-9, points in sorted
    order (a COLMAP model's points come in file order now, in pycolmap's hash order before). The value carries its
    version (``FINGERPRINT_VERSION:`` then the hex digest); a record of another version is not compared."""
    import hashlib

    def rounded(a) -> bytes:
        return (np.round(np.asarray(a, np.float64), 9) + 0.0).tobytes()     # (+ 0.0: -0.0 and 0.0 hash alike)

    h = hashlib.sha256()
    h.update(f"{ds.layout}|{ds.color_space}|{ds.resolution}|".encode())
    h.update(np.asarray(ds.background, np.float64).tobytes())
    for split, views in (("train", ds.train), ("test", ds.test)):
        for v in views:
            c = v.camera
            h.update(f"{split}|{v.name}|{c.width}|{c.height}|".encode())
            h.update(rounded([c.fx, c.fy, c.cx, c.cy]))
            h.update(rounded(c.world_to_camera))
            und = getattr(v.loader, "undistorter", None)
            if und is not None:     # the lens model the images are undistorted with (the pinhole can stay the same)
                d = und.distorted
                h.update(f"{und.model}|{d.width}|{d.height}|{v.loader.source_size}|".encode())
                h.update(rounded(list(d.params)))
            for path in (v.image_path, getattr(v.loader, "mask_path", None)):
                if path is not None:
                    with open(path, "rb") as f:
                        for block in iter(lambda: f.read(1 << 20), b""):
                            h.update(block)
    if ds.points_xyz is not None and ds.points_from == "layout":
        pts = np.concatenate([np.asarray(ds.points_xyz, np.float32).reshape(-1, 3),
                              np.asarray(ds.points_rgb, np.float32).reshape(-1, 3)], axis=1)
        h.update(np.ascontiguousarray(pts[np.lexsort(pts.T[::-1])]).tobytes())
    return f"{FINGERPRINT_VERSION}:{h.hexdigest()}"
