"""The densification strategies by name. ``config.STRATEGIES`` names them and the settings section each reads (the
command line's ``--strategy`` choices come from there); :data:`CLASSES` gives each its class."""

from __future__ import annotations

import numpy as np

from ..config import EMPTY_BACKGROUNDS, STRATEGIES, TrainConfig
from ..data.dataset import Dataset
from ..model.gaussians import Gaussians
from .densify import DefaultStrategy
from .mcmc import MCMCStrategy
from .strategy import Strategy
from .weights import max_weights

#: The class of each strategy that ``config.STRATEGIES`` names (tests/test_cli.py checks that both hold the same names).
CLASSES: dict[str, type[Strategy]] = {"default": DefaultStrategy, "mcmc": MCMCStrategy}


def make_strategy(cfg: TrainConfig, extent: float, white_background: bool, train_cameras=(),
                  empty_background: bool = False) -> Strategy:
    """The densification strategy ``cfg.strategy`` names, built from its section of ``cfg``; ``train_cameras``: the
    training views' cameras, whose blending weights ``densify.weight_prune`` measures (:mod:`.weights`);
    ``empty_background``: whether the run fits an object on an empty background (:func:`empty_background`)."""
    if cfg.strategy not in CLASSES:
        raise ValueError(f"unknown densification strategy {cfg.strategy!r} (expected one of {', '.join(STRATEGIES)})")
    strategy = CLASSES[cfg.strategy].from_config(cfg, extent, white_background, empty_background)
    if isinstance(strategy, DefaultStrategy) and cfg.densify.weight_prune > 0:
        cameras = list(train_cameras)
        if not cameras:
            raise ValueError("densify.weight_prune needs the training cameras")
        strategy.view_weights = lambda g: max_weights(g, cameras, cfg.raster)
    return strategy


def empty_background(setting: str, transparent: bool) -> bool:
    """Whether a run fits an object on an empty background: ``densify.empty_background`` ('on', 'off', or 'auto':
    when ``transparent``, a training image has transparent pixels)."""
    if setting not in EMPTY_BACKGROUNDS:
        raise ValueError(f"densify.empty_background: {setting!r}, expected one of {', '.join(EMPTY_BACKGROUNDS)}")
    return setting == "on" or (setting == "auto" and bool(transparent))


def initial_gaussians(ds: Dataset, sh_degree: int, strategy: Strategy | None = None, seed: int = 0) -> Gaussians:
    """The Gaussians a run starts from: the dataset's points with the strategy's initial opacity and scale factor,
    subsampled (uniformly, ``seed``) to the strategy's bound on the number of Gaussians."""
    if ds.points_xyz is None or len(ds.points_xyz) == 0:
        raise ValueError(f"{ds.root}: the dataset has no initial points")
    xyz, rgb = ds.points_xyz, ds.points_rgb
    cap = None if strategy is None else strategy.max_gaussians
    if cap is not None and len(xyz) > cap:
        keep = np.sort(np.random.default_rng(seed).choice(len(xyz), size=cap, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    if strategy is None:
        return Gaussians.from_points(xyz, rgb, sh_degree=sh_degree)
    return Gaussians.from_points(xyz, rgb, sh_degree=sh_degree, initial_opacity=strategy.init_opacity,
                                 scale_factor=strategy.init_scale)
