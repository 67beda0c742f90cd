"""The densification strategies by name. ``config.STRATEGIES`` names them and the settings section each reads (the
command line's ``--strategy`` choices come from there); :data:`CLASSES` gives each its class."""

from __future__ import annotations

from typing import Callable

import mitsuba as mi
import numpy as np

from ..config import EMPTY_BACKGROUNDS, STRATEGIES, TrainConfig
from ..data.dataset import Dataset
from ..model.gaussians import Gaussians
from .densify import DefaultStrategy
from .mcmc import MCMCStrategy
from .strategy import Strategy
from .schedules import sh_degree_at
from .weights import error_weights, max_weights

#: The class of each strategy that ``config.STRATEGIES`` names (tests/test_cli.py checks that both hold the same names).
CLASSES: dict[str, type[Strategy]] = {"default": DefaultStrategy, "mcmc": MCMCStrategy}


def make_strategy(cfg: TrainConfig, extent: float, white_background: bool, train_cameras=(),
                  empty_background: bool = False, training_views=None, background=(0.0, 0.0, 0.0)) -> Strategy:
    """The densification strategy ``cfg.strategy`` names, built from its section of ``cfg``; ``train_cameras``: the
    training views' cameras, whose blending weights ``densify.weight_prune`` and ``densify.prune_unseen`` measure
    (:mod:`.weights`);
    ``empty_background``: whether the run fits an object on an empty background (:func:`empty_background`);
    ``training_views`` (a :class:`~.targets.TrainingViews`) and the ``background`` the run renders on: the views
    ``densify.error_gate`` scores the model on (:func:`error_scorer`)."""
    if cfg.strategy not in CLASSES:
        raise ValueError(f"unknown densification strategy {cfg.strategy!r} (expected one of {', '.join(STRATEGIES)})")
    strategy = CLASSES[cfg.strategy].from_config(cfg, extent, white_background, empty_background)
    if isinstance(strategy, DefaultStrategy) and (cfg.densify.weight_prune > 0 or cfg.densify.prune_unseen):
        cameras = list(train_cameras)
        if not cameras:
            raise ValueError("densify.weight_prune and densify.prune_unseen need the training cameras")
        strategy.view_weights = lambda g, unit: max_weights(g, cameras, cfg.raster, unit)
        strategy.unseen_weight = float(cfg.raster.alpha_min)
    if isinstance(strategy, DefaultStrategy) and cfg.densify.error_gate > 0:
        if training_views is None or not len(training_views):
            raise ValueError("densify.error_gate needs the training views")
        strategy.view_errors = error_scorer(cfg, training_views, background)
    return strategy


def error_scorer(cfg: TrainConfig, views, background) -> Callable:
    """``(gaussians, step) -> mi.Float``: ``densify.error_gate``'s score (:func:`.weights.error_weights`) on
    ``densify.error_views`` of the training ``views`` (a :class:`~.targets.TrainingViews`), drawn without
    replacement from a stream keyed by the run's seed and the iteration (a resumed run draws the same), rendered at
    the iteration's SH degree on ``background`` (with the views' given poses and without a colour compensation: the
    score looks for what the model has not fitted, and those corrections are small next to it)."""
    d, o = cfg.densify, cfg.optim

    def score(g: Gaussians, step: int) -> "mi.Float":
        n = len(views)
        picks = np.random.default_rng([cfg.seed, 7, step]).choice(n, size=min(n, d.error_views), replace=False)
        chosen = [(views.camera(int(i)), views.target(int(i))) for i in picks]
        degree = min(g.sh_degree, sh_degree_at(step, o.sh_degree, o.sh_increase_interval))
        return error_weights(g, chosen, degree, background, d.error_threshold, cfg.raster)
    return score


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
