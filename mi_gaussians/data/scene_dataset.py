"""A Mitsuba scene file as a training dataset: cameras, path-traced references (cached), initial points.

``load_scene_dataset(scene.xml, cfg, cache_root)`` returns a :class:`~mi_gaussians.data.dataset.Dataset` like the
folder layouts do, so the trainer, ``mi-gs eval`` and the reports treat both alike. Its parts:

- **Loading** the scene file with its ``-D`` parameters: :mod:`mi_gaussians.data.scene_file`.
- **Views** (the scene's sensors, or a seeded rig around it): :mod:`mi_gaussians.data.scene_rig`.
- **References** (rendered with the scene's integrator, cached as EXR files): :mod:`mi_gaussians.data.scene_references`.
- **Colour.** Path-traced references are linear HDR radiance (values above 1 are legitimate). By default training sees
  them sRGB-encoded (the transfer curve continued above 1, nothing clipped; :class:`SrgbEncodedLoader`): the loss then
  weighs errors the way they look, as for photographs, and dark regions are not drowned by highlights; the dataset's
  ``color_space`` is 'srgb', and renders are decoded back to linear for EXR outputs. ``linear=True`` trains on
  radiance itself.
- **Initial points**: :mod:`mi_gaussians.data.scene_init`.

Problems with the scene file (missing, XML syntax error, a referenced file missing, no shapes, a sensor that is not a
pinhole camera) raise ``ValueError`` with one line naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np

from ..config import DataConfig, SceneConfig, TriangulateConfig
from ..imwrite import linear_to_srgb, srgb_to_linear
from . import scene_init
from .camera import Camera
from .dataset import Dataset, View
from .images import ImageLoader
from .scene_file import load_scene
from .scene_references import cache_key, depth_path, render_references, write_rig_file
from .scene_rig import scene_views


class SrgbEncodedLoader:
    """An :class:`ImageLoader` whose linear RGB is sRGB-encoded after compositing (HDR values above 1 are kept)."""

    def __init__(self, base: ImageLoader):
        self.base = base

    def load(self, path):
        rgb, alpha = self.base.load(path)
        return np.ascontiguousarray(linear_to_srgb(np.maximum(rgb, 0.0))), alpha


def _check_key(p: Path, key: str, expect_key: str | None) -> None:
    if expect_key is not None and key != expect_key:
        raise ValueError(f"{p}: the scene, a file it references or its parameters changed since the run's references "
                         f"were rendered (key {key}, the run's {expect_key}); start a new run")


def composite_background(background, linear: bool) -> tuple[tuple, tuple]:
    """(``background`` in the training colour space, its linear value that the references are composited over).

    ``background`` is what the Gaussians are drawn over: the references (linear, premultiplied alpha) are composited
    over its linear value, so that encoded targets show ``background`` itself."""
    bg = tuple(float(b) for b in np.asarray(background, dtype=np.float64).reshape(3))
    bg_linear = bg if linear else tuple(float(b) for b in srgb_to_linear(np.asarray(bg, np.float32)))
    return bg, bg_linear


def reference_view(c: Camera, path: Path, bg_linear: tuple, linear: bool) -> View:
    loader = ImageLoader((c.width, c.height), (c.width, c.height), bg_linear)
    return View(c.name, c, path, loader if linear else SrgbEncodedLoader(loader), depth_path=depth_path(path))


def load_scene_dataset(path: str | os.PathLike, cfg: SceneConfig = SceneConfig(), cache_root: str | os.PathLike = ".",
                       background=(0.0, 0.0, 0.0), test_every: int = DataConfig().test_every, seed: int = 0,
                       progress: bool = True, log: Callable[[str], None] | None = None,
                       expect_key: str | None = None, render_missing: bool = True, farm=None,
                       triangulation: TriangulateConfig = TriangulateConfig()) -> Dataset:
    """Load ``path``, make its cameras, render (or reuse) the references, initialize points: a ``Dataset``.

    ``expect_key``: the references key of an earlier run (``--resume``, ``mi-gs eval``); a scene that no longer
    gives it is refused before anything is rendered. ``render_missing=False`` (the viewer, which wants the cameras):
    references not in the cache are not rendered, and those views' ``image_path`` does not exist. ``farm``: renders
    the missing references elsewhere (``scene_references.render_references``)."""
    p = Path(path)
    scene = load_scene(p, cfg.defines)
    views = scene_views(scene, p, cfg, test_every=test_every, seed=seed)
    key = cache_key(p, views, cfg.defines)
    _check_key(p, key, expect_key)
    if render_missing:              # (before any reference is rendered: a film nobody has memory for is refused)
        from ..memory import check_training

        check_training([(c.width, c.height) for c in views.train], str(p),
                       advice="give a smaller film size (-r W [H]) or fewer views (--views)")
    cache_dir = Path(cache_root) / key
    if render_missing:
        write_rig_file(cache_dir, p, cfg.defines, key, views)
    paths = render_references(scene, views, cache_dir, progress=progress, log=log, render=render_missing, farm=farm)
    bg, bg_linear = composite_background(background, cfg.linear)
    train = [reference_view(c, paths[c.name], bg_linear, cfg.linear) for c in views.train]
    test = [reference_view(c, paths[c.name], bg_linear, cfg.linear) for c in views.test]
    # (SfM and the triangulation run on the composited training images: their caches depend on the background and
    # the colour space)
    tag = "_".join(f"{b:.4g}" for b in bg) + ("_linear" if cfg.linear else "")
    work = cache_dir / (f"sfm_{tag}" if cfg.init == "sfm" else f"triangulated_{tag}")
    try:
        xyz, rgb = scene_init.initial_points(scene, cfg.init, cfg.init_points, train, work, seed=seed,
                                             linear=cfg.linear, log=log, triangulation=triangulation)
    except ValueError as e:
        if str(p) in str(e):
            raise
        raise ValueError(f"{p}: {e}") from None
    return Dataset(root=p, layout="mitsuba", train=train, test=test, points_xyz=xyz, points_rgb=rgb,
                   background=np.asarray(bg, dtype=np.float32), color_space="linear" if cfg.linear else "srgb",
                   references=cache_dir, points_from=cfg.init)
