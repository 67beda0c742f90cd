"""The training images' colour compensation (``--exposure``): which kind a run uses, and where it leaves it.

``affine`` (:class:`.exposure.Exposure`: one 3 x 4 transform per image, the 2024 reference's) or ``bilateral``
(:class:`.bilateral.BilateralGrids`: a grid of them per image, gsplat's). Both offer ``apply(rgb, index)``,
``regularization(index)``, ``learning_rate(step)``, ``set_learning_rate``, ``step(active)`` and ``export`` /
``restore`` for checkpoints. What they learnt belongs to the images, not to the model: it is written beside it,
``exposure.json`` (name -> 3 x 4) or ``exposure_grids.npz`` (``names``, ``grids`` (n, L, H, W, 3, 4)).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import OptimConfig
from ..io_utils import atomic_path
from .. import report, run_folder
from .bilateral import BilateralGrids
from .exposure import Exposure


def make_compensation(cfg: OptimConfig, n_images: int):
    """The compensation ``cfg.exposure`` names for ``n_images`` training images, or None ('off')."""
    if cfg.exposure == "affine":
        return Exposure(n_images, cfg)
    if cfg.exposure == "bilateral":
        return BilateralGrids(n_images, cfg)
    return None


def save_compensation(comp, out: Path, names: list[str]) -> None:
    """Write what ``comp`` learnt for the training images ``names`` into the run folder ``out`` (atomically)."""
    if isinstance(comp, Exposure):
        report.write_json(out / run_folder.EXPOSURE, {n: m.tolist() for n, m in zip(names, comp.matrices())})
    else:
        with atomic_path(out / run_folder.EXPOSURE_GRIDS) as tmp:
            np.savez(tmp, names=np.array(names), grids=comp.grids())
