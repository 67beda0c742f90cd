"""The options of ``mi-gs optimize`` that give training settings, as one table: each option's flags, the settings
(``section.field`` of :class:`~mi_gaussians.config.TrainConfig`) it gives and how. The same table builds the parser,
the configuration of a new run and the check of a resumed one (an option given again with ``--resume`` must agree
with the run's settings, except those that only change how the run goes on).

To add an option: one :class:`Option` in :func:`options` (its default lives in ``config.py``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable

from ..config import (DEPTH_WEIGHT_DECAY, EXPOSURES, INITS, RIGS, SCENE_INITS, STRATEGIES, DataConfig, MCMCConfig,
                      OptimConfig, SceneConfig, SettingError, TrainConfig)
from .args import background, field_of_view, finite_float, non_negative_int, positive_float, positive_int, sh_degree
from .errors import InputError


def _set_fields(cfg: TrainConfig, values: dict) -> TrainConfig:
    """``cfg`` with ``{"section.field": value}`` set."""
    for key, value in values.items():
        section, _, name = key.rpartition(".")
        if section:
            cfg = dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **{name: value})})
        else:
            cfg = dataclasses.replace(cfg, **{name: value})
    return cfg


def setting(cfg: TrainConfig, key: str):
    """The value of the setting ``section.field`` (or a top-level ``field``)."""
    for name in key.split("."):
        cfg = getattr(cfg, name)
    return cfg


@dataclass(frozen=True)
class Option:
    """A command-line option that gives training settings."""

    flags: tuple[str, ...]                   # e.g. ("-r", "--resolution")
    keys: tuple[str, ...]                    # the settings it gives ("section.field")
    kwargs: dict = field(default_factory=dict)   # add_argument's type, nargs, action, choices, help
    # (cfg, value, scene_file) -> cfg for a new run; default: every key set to the value
    give: Callable[[TrainConfig, object, bool], TrainConfig] | None = None
    # (cfg, value) -> cfg on --resume for an option that only changes how the run goes on; None: it must agree
    resume: Callable[[TrainConfig, object], TrainConfig] | None = None
    same: Callable[[object, object], bool] = lambda a, b: a == b    # (given, the run's) agree on --resume
    scene: bool = False                      # an option of a Mitsuba scene input (its own help group)

    @property
    def dest(self) -> str:
        return self.flags[-1].lstrip("-").replace("-", "_")

    @property
    def name(self) -> str:
        return self.flags[-1]

    def apply(self, cfg: TrainConfig, value, scene_file: bool) -> TrainConfig:
        if self.give is not None:
            return self.give(cfg, value, scene_file)
        return _set_fields(cfg, {k: value for k in self.keys})


def _resolution(cfg: TrainConfig, values, scene_file: bool) -> TrainConfig:
    """-r: the film size W [H] of a scene file's cameras, or the divisor of a dataset folder's images."""
    if scene_file:
        if len(values) > 2 or min(values) < 16:
            raise InputError("for a scene .xml, --resolution is the film size in pixels, W [H] (at least 16), "
                             f"not a divisor: got {' '.join(map(str, values))}")
        return _set_fields(cfg, {"scene.resolution": tuple(values)})
    if len(values) != 1:
        raise InputError("-r/--resolution takes one divisor for a dataset folder (e.g. -r 4)")
    return _set_fields(cfg, {"data.resolution": values[0]})


def _init(cfg: TrainConfig, value: str, scene_file: bool) -> TrainConfig:
    """--init: ``scene.init`` for a scene file, ``data.init`` for a dataset folder (each with its own choices)."""
    key, allowed = ("scene.init", SCENE_INITS) if scene_file else ("data.init", INITS)
    if value not in allowed:
        kind = "a scene .xml" if scene_file else "a dataset folder"
        raise InputError(f"--init {value}: for {kind} the initial points are {', '.join(allowed)}")
    return _set_fields(cfg, {key: value})


def _same_defines(a, b) -> bool:
    from ..data.scene_file import parse_defines

    return parse_defines(a) == parse_defines(b)           # (the order of -D is free)


def _store_true(help: str) -> dict:
    return {"action": "store_true", "default": None, "help": help}


def options() -> list[Option]:
    """Every training option, in the order they apply (a later one wins: --background over --white-background)."""
    from ..data.scene_rig import FALLBACK_FOV, FALLBACK_RESOLUTION, FALLBACK_SPP, FALLBACK_UP

    d, o, t, sc, mc = DataConfig(), OptimConfig(), TrainConfig(), SceneConfig(), MCMCConfig()
    return [
        Option(("--iterations",), ("optim.iterations",), {
            "type": positive_int, "help": f"default {o.iterations} (the paper's); a shorter run keeps the paper's "
                                          "proportions (densification until half of it)"},
               give=lambda cfg, n, _: cfg.with_iterations(n),
               resume=lambda cfg, n: _set_fields(cfg, {"optim.iterations": n})),
        Option(("-r", "--resolution"), ("data.resolution", "scene.resolution"), {
            "type": positive_int, "nargs": "+",
            "help": f"scene folder: divide the image size by this (default {d.resolution}); scene .xml: the film size "
                    f"of generated cameras, W [H] (default: the scene's sensor's, else {FALLBACK_RESOLUTION[0]})"},
               give=_resolution),
        Option(("--white-background",), ("data.background",), _store_true("composite RGBA images over white"),
               give=lambda cfg, _, __: _set_fields(cfg, {"data.background": (1.0, 1.0, 1.0)})),
        Option(("--background",), ("data.background",), {
            "type": finite_float, "nargs": "+", "help": "background colour (1 or 3 values)"},
               give=lambda cfg, v, _: _set_fields(cfg, {"data.background": background(v)})),
        Option(("--random-background",), ("optim.random_background",),
               _store_true("random background colour per iteration")),
        Option(("--absgrad",), ("densify.absgrad",), _store_true(
            "densify on AbsGS's absolute per-pixel gradients (gsplat's absgrad), with its own threshold "
            "(densify.absgrad_threshold, default 0.0008)")),
        Option(("--depth-weight",), ("optim.depth_weight", "optim.depth_weight_final"), {
            "type": positive_float,
            "help": "scene .xml: add an inverse-depth L1 against the exact depth Mitsuba gives, weighted W at the "
                    f"start and decaying to W/{DEPTH_WEIGHT_DECAY:g} (the 2024 reference's schedule with W = 1)"},
               give=lambda cfg, w, _: dataclasses.replace(cfg, optim=cfg.optim.with_depth_weight(w))),
        Option(("--exposure",), ("optim.exposure",), {
            "nargs": "?", "const": "affine", "choices": tuple(e for e in EXPOSURES if e != "off"),
            "help": "compensate each training image's exposure and white balance: 'affine' (the default when given "
                    "alone), a 3x4 colour transform per image applied to the render before the loss (the 2024 "
                    "reference's --train_test_exp), saved in exposure.json; 'bilateral', a grid of them over the "
                    "image and its brightness (gsplat's bilateral grid), saved in exposure_grids.npz; never in the "
                    "model; the test views are then also scored the reference's way (a transform fitted on their "
                    "left half, the right half scored)"}),
        Option(("--pose-opt",), ("optim.pose_opt",), _store_true(
            "refine the training cameras with the Gaussians (gsplat's pose_opt: a rotation and translation per "
            f"camera, sparse Adam at {o.pose_opt_lr:g}, optim.pose_opt_lr); the refined cameras are written to "
            "cameras_refined.json and images_refined.txt, test cameras stay as given")),
        Option(("--strategy",), ("strategy",), {
            "choices": tuple(STRATEGIES),
            "help": "densification: 'default' (the paper's clone / split / prune) or 'mcmc' (3DGS as Markov Chain "
                    "Monte Carlo, gsplat's MCMCStrategy: relocation, growth up to --max-gaussians)"}),
        Option(("--max-gaussians",), ("mcmc.cap_max",), {
            "type": positive_int, "help": f"--strategy mcmc: the most Gaussians the run may have "
                                          f"(default {mc.cap_max:,})"}),
        Option(("--antialiased",), ("raster.antialiased",), _store_true(
            "Mip-Splatting's 2D filter (gsplat's antialiased mode); the model must then be rendered with it, which "
            "config.json and gaussians.xml record")),
        Option(("--sh-degree",), ("optim.sh_degree",), {
            "type": sh_degree, "help": f"maximum SH degree (default {o.sh_degree})"}),
        Option(("--test-every",), ("data.test_every",), {
            "type": non_negative_int, "help": f"hold out every N-th image (COLMAP/ngp; 0: none; default "
                                              f"{d.test_every})"}),
        Option(("--random-points",), ("data.random_points",), {
            "type": positive_int, "help": f"initial random points for layouts without SfM points "
                                          f"(default {d.random_points})"}),
        Option(("--seed",), ("seed", "data.seed"), {
            "type": non_negative_int, "help": f"seed of every random choice of the run (default {t.seed})"}),
        Option(("--checkpoint-every",), ("checkpoint_every",), {
            "type": positive_int, "help": f"write a checkpoint (what --resume continues from) every N iterations "
                                          f"(default {t.checkpoint_every})"},
               resume=lambda cfg, n: _set_fields(cfg, {"checkpoint_every": n})),
        Option(("--eval-every",), ("eval_every",), {
            "type": non_negative_int, "help": f"test PSNR for the curves every N iterations (default "
                                              f"{t.eval_every}; 0: at the end only)"},
               resume=lambda cfg, n: _set_fields(cfg, {"eval_every": n})),
        # a Mitsuba scene file
        Option(("--rig",), ("scene.rig",), {
            "choices": RIGS, "help": f"cameras: the scene's sensors, or generated around its bounding box "
                                     f"(default {sc.rig}: the sensors if the scene declares several, else "
                                     "hemisphere)"}, scene=True),
        Option(("--views",), ("scene.views",), {
            "type": positive_int, "help": f"generated training cameras (default {sc.views}; --seed also picks the "
                                          "rig, so another seed renders new references)"}, scene=True),
        Option(("--test-views",), ("scene.test_views",), {
            "type": non_negative_int, "help": f"generated held-out cameras (default {sc.test_views})"}, scene=True),
        Option(("--radius",), ("scene.radius",), {
            "type": positive_float, "help": "rig radius (default: the bounding sphere fills the view)"}, scene=True),
        Option(("--fov",), ("scene.fov",), {
            "type": field_of_view, "help": f"horizontal field of view in degrees (default: the sensor's, else "
                                           f"{FALLBACK_FOV:g})"}, scene=True),
        Option(("--up",), ("scene.up",), {
            "type": finite_float, "nargs": 3, "help": f"world up (default: the sensor's, else "
                                                      f"{' '.join(f'{u:g}' for u in FALLBACK_UP)})"},
               give=lambda cfg, v, _: _set_fields(cfg, {"scene.up": tuple(v)}), scene=True),
        Option(("--spp",), ("scene.spp",), {
            "type": positive_int, "help": f"reference samples per pixel (default: the sensor's, else "
                                          f"{FALLBACK_SPP})"}, scene=True),
        Option(("--linear",), ("scene.linear",), _store_true(
            "train on linear radiance (default: on the sRGB-encoded references)"), scene=True),
        Option(("--init",), ("data.init", "scene.init"), {
            "choices": tuple(dict.fromkeys(INITS + SCENE_INITS)), "metavar": "INIT",
            "help": f"initial points. A dataset folder: {' | '.join(INITS)} (default {d.init}: the dataset's own "
                    "points, else triangulated from the posed images, else the random cube); a scene .xml: "
                    f"{' | '.join(SCENE_INITS)} (default {sc.init}: sampled on the shapes and coloured by the "
                    "references, random in the bounding box, triangulated from the references with the scene's "
                    "exact cameras, or structure from motion)"},
               give=_init),
        Option(("--init-points",), ("scene.init_points",), {
            "type": positive_int, "help": f"initial points for shapes/random (default {sc.init_points})"},
               scene=True),
        Option(("-D", "--define"), ("scene.defines",), {
            "action": "append", "metavar": "KEY=VALUE",
            "help": "set a scene parameter (<default name=\"KEY\">), as mitsuba -D; repeatable"},
               give=lambda cfg, v, _: _set_fields(cfg, {"scene.defines": tuple(v)}), same=_same_defines,
               scene=True),
    ]


def add_arguments(parser) -> dict:
    """Add every option of the table to ``parser``; returns the argument groups ({"training", "scene"})."""
    groups = {"training": parser, "scene": parser.add_argument_group("Mitsuba scene (.xml) input")}
    for opt in options():
        groups["scene" if opt.scene else "training"].add_argument(*opt.flags, dest=opt.dest, **{
            "default": None, **opt.kwargs})
    return groups


def given(args) -> list[Option]:
    """The options given on the command line (every option of the table defaults to None)."""
    return [opt for opt in options() if getattr(args, opt.dest, None) is not None]


def _flags_of(key: str) -> str:
    names = [opt.name for opt in options() if key in opt.keys]
    return f" ({', '.join(names)})" if names else ""


def explain(e: SettingError) -> InputError:
    """A setting's error as the user's input error, naming the options that give the setting."""
    return InputError(f"setting {e.key!r}{_flags_of(e.key)}: {e.problem}")


def new_run_config(args, scene_file: bool) -> TrainConfig:
    """The settings of a new run: the defaults, then the options given, then ``--set`` (checked: one line naming
    the setting and its option). A setting given that has no effect in this run is said in a note
    (:func:`mi_gaussians.setting_effects.inert`)."""
    cfg = TrainConfig()
    chosen = given(args)
    for opt in chosen:
        cfg = opt.apply(cfg, getattr(args, opt.dest), scene_file)
    settings = args.settings or ()
    keys = [k for opt in chosen if opt.resume is None for k in opt.keys]
    keys += [str(text).partition("=")[0].strip() for text in settings]
    try:
        cfg = cfg.with_settings(settings).check(scene_file, given=keys)
    except SettingError as e:
        raise explain(e) from None
    note_inert(cfg, chosen, args, settings, scene_file)
    return cfg


def _keys_set(opt: Option, value, scene_file: bool) -> list[str]:
    """The settings an option given with ``value`` sets: its one key, or those of its keys it changes (``-r`` sets
    data.resolution for a dataset folder, scene.resolution for a scene file)."""
    if len(opt.keys) == 1:
        return list(opt.keys)
    base = TrainConfig()
    try:
        changed = opt.apply(base, value, scene_file)
    except (InputError, SettingError, ValueError):
        return []
    return [k for k in opt.keys if setting(changed, k) != setting(base, k)]


def note_inert(cfg: TrainConfig, chosen, args, settings, scene_file: bool) -> list[str]:
    """One note on stderr for each option or ``--set`` setting with no effect in a run of ``cfg``; returns them."""
    from ..setting_effects import inert
    from .errors import note

    origin = {}                                   # setting -> how it was given
    for opt in chosen:
        for key in _keys_set(opt, getattr(args, opt.dest), scene_file):
            origin.setdefault(key, f"{opt.name} ({key})")
    for text in settings:
        key = str(text).partition("=")[0].strip()
        origin[key] = f"--set {key}"
    lines = [f"{origin[key]} has no effect in this run: {why}" for key, why in inert(cfg, list(origin), scene_file)]
    for line in lines:
        note(line)
    return lines


def resumed_config(args, run: TrainConfig, scene_file: bool, where: str) -> TrainConfig:
    """The settings of a run being resumed (``run``, from ``where``: its config.json): an option given again must
    agree with them, except those that change only how the run goes on (``--iterations`` may move its end; its
    schedules stay the run's)."""
    differ, cfg = [], run
    for opt in given(args):
        value = getattr(args, opt.dest)
        if opt.resume is not None:
            cfg = opt.resume(cfg, value)
            continue
        asked = opt.apply(TrainConfig(), value, scene_file)
        differ += [f"{opt.name} gives {key} = {setting(asked, key)!r}, the run has {setting(run, key)!r}"
                   for key in opt.keys if not opt.same(setting(asked, key), setting(run, key))]
    if differ:
        raise InputError(f"--resume: {where}: the options differ from the run's settings: {'; '.join(differ)} "
                         "(resume without them, or start a new run)")
    try:
        return cfg.validate()
    except SettingError as e:
        raise explain(e) from None
