"""The training views as a step takes them: each view's camera (``ViewParams``) and target -- the image over the
run's fixed background, its transparency (1 - alpha) where a random background or the alpha loss needs it, its
inverse exact depth with ``--depth-weight`` -- at full resolution, or at an integer scale of the coarse-to-fine
schedule (:mod:`.resolution`, ``optim.coarse_to_fine``).

Targets are decoded once and kept as Dr.Jit tensors (copied into Dr.Jit-owned memory). A scale's targets are their
area-averages to that size, made when the run reaches the scale (one host round trip per image and scale, a few
times per run) and dropped when it leaves it.
"""

from __future__ import annotations

import numpy as np

from ..config import TrainConfig
from ..data.dataset import Dataset
from ..data.images import resize_area
from ..drjit_utils import owned_tensor
from ..raster.projection import ViewParams
from .losses import inverse_depth_target
from .resolution import ResolutionSchedule, scaled_size, spectrum_schedule


class TrainingViews:
    def __init__(self, ds: Dataset, cfg: TrainConfig):
        o = cfg.optim
        self.cameras = [v.camera for v in ds.train]
        #: whether a training image has transparent pixels (alpha below 1/2: an object on an empty background, whose
        #: rules densify.empty_background 'auto' turns on)
        self.transparent = False
        keep_alpha = o.random_background or o.alpha_weight > 0      # (else each alpha is dropped once looked at)
        images, alphas, brightest = [], [], 0.0
        for v in ds.train:
            image, alpha = v.loader.load(v.image_path)      # (one decode for both; View.load_image / load_alpha)
            brightest = max(brightest, float(np.max(image, initial=0.0)))
            images.append(image)
            self.transparent = self.transparent or (alpha is not None and float(np.min(alpha, initial=1.0)) < 0.5)
            if keep_alpha:
                alphas.append(alpha)
        if brightest <= 1e-6:
            raise ValueError(f"{ds.root}: every training image is black: there is nothing to fit (a scene whose "
                             "lights are missing, hidden or turned off by its -D values?)")
        self.schedule = ResolutionSchedule((), (), 0)
        if o.coarse_to_fine == "spectrum":
            until = o.coarse_until if o.coarse_until > 0 else cfg.densify.densify_until_iter
            self.schedule = spectrum_schedule(images, min(until, o.iterations))
        self.targets = [owned_tensor(im) for im in images]
        del images
        self.depth_targets = None
        if o.depth_weight > 0:
            depths = [v.load_depth() for v in ds.train]
            if any(d is None for d in depths):
                raise ValueError(f"{ds.root}: depth supervision (--depth-weight) needs the exact depth of a Mitsuba "
                                 "scene (.xml); this dataset has none")
            self.depth_targets = [owned_tensor(inverse_depth_target(d)) for d in depths]
        # 1 - alpha of each training image: to re-composite it over a random background, and for the alpha loss
        # (only where an image has alpha: on opaque images it would ask for nothing but full coverage)
        self.transparency = None
        if keep_alpha:
            alphas = [np.ones((c.height, c.width), np.float32) if a is None else a
                      for a, c in zip(alphas, self.cameras)]
            if o.random_background or any(float(np.min(a, initial=1.0)) < 1.0 for a in alphas):
                self.transparency = [owned_tensor(1.0 - a[..., None]) for a in alphas]
        del alphas
        self.scale = 1
        self._scaled: dict = {}                     # the current scale's targets, by kind (made on first use)
        self._views: dict = {}                      # (scale, view) -> ViewParams, built on first use

    def __len__(self) -> int:
        return len(self.cameras)

    # ------------------------------------------------------------------ scale
    def scale_at(self, step: int) -> int:
        """The coarse-to-fine scale of (1-based) iteration ``step`` (1: full resolution)."""
        return self.schedule.scale_at(step)

    def set_scale(self, scale: int) -> None:
        """Make ``scale`` the current one (the targets of another scale are dropped)."""
        if scale != self.scale:
            self.scale, self._scaled = int(scale), {}

    def _at_scale(self, kind: str, full: list, idx: int):
        if self.scale == 1 or full is None:
            return None if full is None else full[idx]
        per_view = self._scaled.setdefault(kind, [None] * len(self.cameras))
        if per_view[idx] is None:
            c = self.cameras[idx]
            w, h = scaled_size(c.width, c.height, self.scale)
            a = np.array(full[idx], dtype=np.float32)
            flat = a.ndim == 2
            small = resize_area(a[..., None] if flat else a, w, h)
            per_view[idx] = owned_tensor(small[..., 0] if flat else small)
        return per_view[idx]

    # ------------------------------------------------------------------ what a step takes
    def target(self, idx: int):
        """View ``idx``'s image over the fixed background, at the current scale."""
        return self._at_scale("image", self.targets, idx)

    def transparency_of(self, idx: int):
        """View ``idx``'s 1 - alpha at the current scale (None without)."""
        return self._at_scale("transparency", self.transparency, idx)

    def depth_of(self, idx: int):
        """View ``idx``'s inverse exact depth at the current scale (None without)."""
        return self._at_scale("depth", self.depth_targets, idx)

    def camera(self, idx: int):
        """View ``idx``'s camera at the current scale."""
        c = self.cameras[idx]
        return c if self.scale == 1 else c.scaled(*scaled_size(c.width, c.height, self.scale))

    def view(self, idx: int) -> ViewParams:
        """View ``idx``'s camera as opaque Dr.Jit values, at the current scale."""
        key = (self.scale, idx)
        if key not in self._views:
            self._views[key] = ViewParams.from_camera(self.camera(idx))
        return self._views[key]
