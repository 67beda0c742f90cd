"""What the viewer lists beside a model: the cameras of its dataset (:class:`ViewEntry`: a camera, its reference image
and, for a training view of a run with ``--exposure``, its colour transform or bilateral grid), read from a run folder
or a dataset, and a camera to start from when there are none."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .data.camera import Camera


@dataclass
class ViewEntry:
    """A camera of the model's dataset, with a loader of its reference image ((H, W, 3) display-encoded floats) and,
    for a training view of a run with ``--exposure``, a getter of its colour transform (3 x 4, or a bilateral grid
    (L, H, W, 3, 4))."""

    name: str
    camera: Camera
    reference: Callable[[], np.ndarray] | None = None
    exposure: Callable[[], np.ndarray] | None = None


def default_camera(g) -> Camera:
    """A camera looking along +z at a model's centre from 2.5 times its radius (90 % of the centres inside)."""
    means = np.array(g.means, np.float64).reshape(-1, 3)
    centre = np.median(means, axis=0)
    radius = float(np.percentile(np.linalg.norm(means - centre, axis=1), 90)) or 1.0
    w2c = np.eye(4)
    w2c[:3, 3] = -(centre - [0.0, 0.0, 2.5 * radius])
    return Camera(width=800, height=600, fx=600.0, fy=600.0, cx=400.0, cy=300.0, world_to_camera=w2c, name="default")


def dataset_entries(ds, exposure: Callable[[], dict] | None = None) -> list[ViewEntry]:
    """The camera list of a dataset's training and test views, each with its reference when the image exists;
    ``exposure``: a getter of the training views' colour transforms (name -> 3 x 4 or bilateral grid) of a run with
    ``--exposure``."""
    def getter(name):
        return None if exposure is None else (lambda: exposure()[name])

    return [ViewEntry(f"{kind} {v.name}", v.camera, v.load_image if Path(v.image_path).is_file() else None,
                      getter(v.name) if kind == "train" else None)
            for kind, views in (("train", ds.train), ("test", ds.test)) for v in views]


def run_entries(record, out, warn: Callable[[str], None]) -> tuple[list[ViewEntry], str, tuple]:
    """(camera list, colour space, background) of the dataset the run in ``out`` (its ``RunRecord``) was trained
    on. A scene file's references are not rendered again: views whose reference is gone are listed without a
    picture. A dataset that cannot be loaded any more gives no cameras, and a line to ``warn``."""
    from .run_folder import EXPOSURE, EXPOSURE_GRIDS
    from .runs import run_dataset

    try:
        ds = run_dataset(record, out, render_missing=False)
    except (ValueError, OSError, RuntimeError) as e:
        warn(f"the run's dataset cannot be loaded ({e}); viewing without its cameras")
        return [], "srgb", tuple(record.train.data.background)
    kind = record.train.optim.exposure                  # (the file the run wrote: a leftover of another is not read)
    path = Path(out) / (EXPOSURE if kind == "affine" else EXPOSURE_GRIDS)
    transforms = (_exposures(path, warn) if kind == "affine" else _grids(path, warn) if kind == "bilateral" else None)
    if transforms is not None and set(transforms) != {v.name for v in ds.train}:
        warn(f"{path}: does not match the run (its {len(transforms)} views are not the run's {len(ds.train)} training "
             "views); the views are shown without their exposure")
        transforms = None
    return (dataset_entries(ds, None if transforms is None else lambda: transforms), ds.color_space,
            tuple(float(b) for b in ds.background))


def _exposures(path, warn) -> dict | None:
    """The colour transforms of ``exposure.json`` (name -> 3 x 4 array), or None (absent, or unreadable: warned)."""
    import json

    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        out = {str(k): np.asarray(v, np.float64).reshape(3, 4) for k, v in data.items()}
        if not all(np.all(np.isfinite(m)) for m in out.values()):
            raise ValueError("non-finite values")
    except (OSError, ValueError, TypeError, AttributeError) as e:
        warn(f"{path}: not readable ({e}); the views are shown without their exposure")
        return None
    return out


def _grids(path, warn) -> dict | None:
    """The bilateral grids of ``exposure_grids.npz`` (name -> (L, H, W, 3, 4) array), or None (absent, or
    unreadable: warned)."""
    import zipfile

    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            names, grids = [str(n) for n in z["names"]], np.asarray(z["grids"], np.float64)
        if grids.ndim != 6 or grids.shape[0] != len(names) or grids.shape[-2:] != (3, 4):
            raise ValueError(f"grids of shape {grids.shape} for {len(names)} names")
        if not np.all(np.isfinite(grids)):
            raise ValueError("non-finite values")
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        warn(f"{path}: not readable ({' '.join(str(e).split())[:120] or type(e).__name__}); the views are shown "
             "without their exposure")
        return None
    return dict(zip(names, grids))
