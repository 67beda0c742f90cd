"""The densification strategies by name. ``config.STRATEGIES`` names them and the settings section each reads (the
command line's ``--strategy`` choices come from there); :data:`CLASSES` gives each its class."""

from __future__ import annotations

from ..config import STRATEGIES, TrainConfig
from .densify import DefaultStrategy
from .mcmc import MCMCStrategy
from .strategy import Strategy

#: The class of each strategy that ``config.STRATEGIES`` names (tests/test_cli.py checks that both hold the same names).
CLASSES: dict[str, type[Strategy]] = {"default": DefaultStrategy, "mcmc": MCMCStrategy}


def make_strategy(cfg: TrainConfig, extent: float, white_background: bool) -> Strategy:
    """The densification strategy ``cfg.strategy`` names, built from its section of ``cfg``."""
    if cfg.strategy not in CLASSES:
        raise ValueError(f"unknown densification strategy {cfg.strategy!r} (expected one of {', '.join(STRATEGIES)})")
    return CLASSES[cfg.strategy].from_config(cfg, extent, white_background)
