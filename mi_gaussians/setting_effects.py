"""Settings that have no effect in a run: a setting the user gave that the run's other settings (or its input) make
inert is said in a note, not silently ignored (a pose rate without ``--pose-opt``, the bilateral grid's size with the
affine exposure, a scene's rig for a dataset folder). A setting of another densification strategy is refused instead
(``TrainConfig.check``).

One table, :data:`RULES`: a setting (``section.field``, or ``section.*`` for every field of a section) and when it has
no effect. :func:`inert` applies it to the settings given for one run; ``mi-gs optimize`` (``cli/train_options.py``)
and the sweep's spec check (``cluster/sweep_spec.py``) both print its notes.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from typing import Callable

from .config import TrainConfig


@dataclass(frozen=True)
class Rule:
    """``pattern`` (``section.field``, ``fnmatch`` wildcards) has no effect when ``unused(cfg, scene_file)`` returns a
    reason (the words after "no effect: ...")."""

    pattern: str
    unused: Callable[[TrainConfig, bool], str | None]


def _unless(condition: Callable[[TrainConfig, bool], bool], reason: str):
    return lambda cfg, scene_file: None if condition(cfg, scene_file) else reason


_POSE = _unless(lambda c, _: c.optim.pose_opt, "it applies to --pose-opt (optim.pose_opt), which this run does not use")
_AFFINE = _unless(lambda c, _: c.optim.exposure == "affine",
                  "it applies to --exposure affine, and this run's optim.exposure is {exposure}")
_BILATERAL = _unless(lambda c, _: c.optim.exposure == "bilateral",
                     "it applies to --exposure bilateral, and this run's optim.exposure is {exposure}")
_SCENE = _unless(lambda _, scene_file: scene_file,
                 "it configures a Mitsuba scene (.xml) input, and this run trains on a dataset folder")
_FOLDER = _unless(lambda _, scene_file: not scene_file,
                  "it configures a dataset folder, and this run trains on a Mitsuba scene (.xml), whose film size is "
                  "-r W H (scene.resolution) and whose initial points are scene.init")
_TRIANGULATED = _unless(lambda c, scene_file: c.scene.init == "triangulate" if scene_file
                        else c.data.init in ("auto", "triangulate"),
                        "initial points are triangulated only with data.init auto or triangulate (a dataset folder) "
                        "or scene.init triangulate (a Mitsuba scene); this run's are not")

#: Every setting that may have no effect, and when. (The order is that of the notes.)
RULES = (
    Rule("optim.pose_opt_*", _POSE),
    Rule("optim.exposure_lr_*", _AFFINE),
    Rule("optim.exposure_grid*", _BILATERAL),
    Rule("optim.depth_weight_final", _unless(lambda c, _: c.optim.depth_weight > 0,
                                             "it is where --depth-weight (optim.depth_weight) decays to, and this run "
                                             "has no depth supervision")),
    Rule("optim.position_lr_delay_mult", _unless(lambda c, _: c.optim.position_lr_delay_steps > 0,
                                                 "it scales the position rate's ramp, and "
                                                 "optim.position_lr_delay_steps is 0 (no ramp)")),
    Rule("optim.sh_increase_interval", _unless(lambda c, _: c.optim.sh_degree > 0,
                                               "the run's SH degree is 0 (optim.sh_degree): there is no degree to "
                                               "raise")),
    Rule("densify.absgrad_threshold", _unless(lambda c, _: c.densify.absgrad,
                                              "it is the threshold of --absgrad (densify.absgrad), which this run does "
                                              "not use (its threshold is densify.grad_threshold)")),
    Rule("densify.grad_threshold", _unless(lambda c, _: not c.densify.absgrad,
                                           "with --absgrad the threshold is densify.absgrad_threshold")),
    *(Rule(key, _unless(lambda c, _: c.strategy == "default" and c.densify.densify_until_iter < c.optim.iterations,
                        "it acts at densify.densify_until_iter in the default strategy, which this run does not reach "
                        "or use"))
      for key in ("densify.weight_prune", "densify.prune_unseen")),
    Rule("densify.error_[tv]*", _unless(lambda c, _: c.densify.error_gate > 0,      # error_views, error_threshold
                                        "it tunes densify.error_gate's score, and the gate is 0 (off)")),
    Rule("densify.empty_screen_fraction", _unless(lambda c, _: c.densify.empty_background != "off"
                                                  and c.densify.max_screen_fraction == 0,
                                                  "it is the screen-size prune on an empty background when "
                                                  "densify.max_screen_fraction is 0, and this run has "
                                                  "densify.empty_background off or its own max_screen_fraction")),
    Rule("scene.*", _SCENE),
    Rule("data.resolution", _FOLDER),
    Rule("data.init", _FOLDER),
    Rule("data.random_points", _FOLDER),
    Rule("data.masks", _FOLDER),
    Rule("data.random_points", _unless(lambda c, _: c.data.init not in ("points", "triangulate"),
                                       "data.init {init} starts from no random points")),
    Rule("triangulate.*", _TRIANGULATED),
)


def inert(cfg: TrainConfig, given, scene_file: bool) -> list[tuple[str, str]]:
    """(setting, why it has no effect) for each of ``given`` (``section.field`` keys the user set) that has none in a
    run of ``cfg`` on a scene file (``scene_file``) or a dataset folder; each setting once, with its first reason."""
    out: dict[str, str] = {}
    for key in dict.fromkeys(given):
        for rule in RULES:
            if key not in out and fnmatch.fnmatchcase(key, rule.pattern):
                reason = rule.unused(cfg, scene_file)
                if reason is not None:
                    out[key] = reason.format(exposure=cfg.optim.exposure, init=cfg.data.init)
    return list(out.items())
