"""Every default of mi-gaussians, in frozen dataclasses, and the values each setting may take: the only home of both
(the command line, ``config.json`` and the library read them here).

Values follow the 3DGS paper and its reference implementation (``docs/conventions.md``); where we differ on purpose,
the field's comment says so. :data:`RULES` gives each setting's range or choices (every other number must be >= 0);
:meth:`TrainConfig.validate` applies them, :meth:`TrainConfig.check` adds the rules that relate settings to each
other and to the input, :meth:`TrainConfig.from_dict` reads a saved record (types checked, JSON values only) and
:meth:`TrainConfig.with_settings` applies ``--set SECTION.FIELD=VALUE`` texts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from .setting_values import SettingError, json_value, parse_value, shown

#: The densification strategies ``TrainConfig.strategy`` may name, each with the section of :class:`TrainConfig` it
#: reads (``mi_gaussians.optim.strategies`` gives each its class; a test checks that both list the same names).
STRATEGIES = {"default": "densify", "mcmc": "mcmc"}
#: ``DataConfig.init``: where a run's initial points come from. 'auto': the layout's own points (COLMAP) when it has
#: them, else triangulated from the posed images (joined by the random ones when the images have alpha: an object on an
#: empty background; runs.initial_points), else (too few) the random cube; 'points' the layout's own only;
#: 'triangulate' always; 'cube' and 'frustum' random (RANDOM_INITS, data/pointcloud.py).
INITS = ("auto", "points", "triangulate", "cube", "frustum")
#: The random samplers among them (where the initial random points of layouts without points lie).
RANDOM_INITS = ("cube", "frustum")
#: ``SceneConfig.rig``: the cameras of a Mitsuba scene.
RIGS = ("auto", "sensors", "hemisphere", "sphere")
#: ``SceneConfig.init``: the initial points of a Mitsuba scene.
SCENE_INITS = ("shapes", "random", "triangulate", "sfm")
#: ``OptimConfig.exposure``: per-image colour compensation ('affine': the 2024 reference's --train_test_exp;
#: 'bilateral': gsplat's bilateral grids).
EXPOSURES = ("off", "affine", "bilateral")
#: ``DataConfig.extent``: how a run measures its scene's length scale (data/pointcloud.py ``scene_extent``): 'depth'
#: the depth at which the cameras see the initial points (the default), 'scene' the larger of that and the cameras'
#: spread, 'cameras' the spread alone (the reference's, gsplat's).
EXTENTS = ("scene", "cameras", "depth")
#: densify.empty_background: the rules for an object on an empty background ('auto': when the images have transparent
#: pixels; optim/densify.py)
EMPTY_BACKGROUNDS = ("auto", "on", "off")
#: ``OptimConfig.pose_opt_pivot``: where a pose correction turns its camera (optim/pose.py).
POSE_PIVOTS = ("centre", "depth")
#: ``OptimConfig.ssim_padding``: 'same', the reference's SSIM (zero padding, the mean over every pixel); 'valid',
#: gsplat's trainer (``fused_ssim(padding="valid")``: the mean over the pixels whose window lies inside the image).
SSIM_PADDINGS = ("same", "valid")
#: ``RasterConfig.footprint``: the tiles a Gaussian is blended in (raster/footprint.py): 'ellipse', those its
#: alpha >= alpha_min ellipse reaches; 'box', every tile of that ellipse's bounding box. Same image and gradients.
FOOTPRINTS = ("ellipse", "box")
#: ``RasterConfig.lanes``: how training maps the blend's pixels to lanes (raster/blend.py): 'balanced', the layout
#: the tiles' load calls for (``balanced_layout``: on CUDA fewer pixels per lane when one tile holds a large share of
#: the instances, on the CPU smaller tiles while the Gaussians are a few pixels wide); 'fixed', the backend's one
#: layout. The speed only: the same images, gradients up to float sums.
LANES = ("balanced", "fixed")
#: ``OptimConfig.coarse_to_fine``: 'off' (every iteration at full resolution, the reference), 'spectrum'
#: (DashGaussian's schedule from the images' Fourier spectra: optim/resolution.py).
COARSE_TO_FINE = ("off", "spectrum")
#: ``OptimConfig.row_order``: the order of the model's rows (Gaussians) while it trains (optim/row_order.py):
#: 'spatial', sorted by where they are after each densification, so that the Gaussians a tile blends lie near one
#: another in memory; 'creation', the order densification makes them in (the reference's). The speed only: the
#: same renders of the same model, a densification's random draws falling to other rows.
ROW_ORDERS = ("spatial", "creation")
#: ``--depth-weight W`` decays from W to W / DEPTH_WEIGHT_DECAY (the 2024 reference's 1.0 to 0.01).
DEPTH_WEIGHT_DECAY = 100.0


@dataclass(frozen=True)
class DataConfig:
    resolution: int = 1                      # -r: divide the image size by 1, 2, 4 or 8 (images_N folders when present)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # RGBA images are composited over this colour
    test_every: int = 8                      # COLMAP / single-transforms layouts: index % test_every == 0 is test (0: no test split)
    init: str = "auto"                       # initial points (INITS): the layout's own, else triangulated from the
                                             # posed images (data/triangulate.py; + the random ones when the images
                                             # have alpha), else the reference's random cube
    random_points: int = 100_000             # random initial points ('cube', 'frustum', and those of 'auto')
    masks: bool = True                       # COLMAP layout: composite each image over the background through its
                                             # mask in masks/ (white = object) when that folder exists
    seed: int = 0
    extent: str = "depth"                    # the length scale that position rates, the clone/split boundary and the
                                             # large-Gaussian prune are fractions of (EXTENTS): 'depth', the depth the
                                             # cameras see the initial points at; 'scene', the larger of that and the
                                             # cameras' spread; 'cameras', 1.1 x the cameras' spread alone (the
                                             # reference, gsplat)
    pose_noise: tuple[float, float] = (0.0, 0.0)   # (degrees, fraction of the scene extent): every training camera
                                             # turned by exactly this angle about a random axis through its centre and
                                             # moved this far in a random direction (seeded by data.seed); test
                                             # cameras stay exact. To measure --pose-opt (data/pose_noise.py)


@dataclass(frozen=True)
class TriangulateConfig:
    """Initial points triangulated from a dataset's posed training images (``data.init`` 'auto' or 'triangulate':
    ``mi_gaussians.data.triangulate``), with COLMAP's filters."""

    neighbours: int = 12                     # each camera is matched with this many near ones looking the same way,
    exhaustive_below: int = 30               # ... or with every other camera when there are at most this many images
    max_features: int = 8192                 # SIFT features per image (COLMAP's default)
    max_reprojection_error: float = 2.0      # pixels: points that reproject worse are dropped
    min_angle: float = 1.5                   # degrees: points triangulated at a smaller angle are dropped (COLMAP's)
    min_track_length: int = 2                # points seen by fewer images are dropped
    min_points: int = 100                    # fewer points than this: too few to start from ('auto' uses the cube)


@dataclass(frozen=True)
class ConvertConfig:
    """Structure from motion (``mi_gaussians.data.convert``), the reference convert.py's choices on pycolmap."""

    camera_model: str = "OPENCV"             # COLMAP model of the shared camera (reference: OPENCV)
    single_camera: bool = True               # one camera for all images (reference: --ImageReader.single_camera 1)
    max_image_size: int = 3200               # SIFT extraction: larger images are downscaled (COLMAP 3.x default)
    max_num_features: int = 8192             # SIFT features per image (COLMAP's default)
    num_threads: int = -1                    # -1: all cores
    resize: bool = False                     # also write images_2/4/8 (reference: --resize)
    seed: int = 0                            # mapper random seed


@dataclass(frozen=True)
class RasterConfig:
    near_plane: float = 0.2                  # cull Gaussians with view-space z <= near_plane
    guard_band: float = 1.3                  # the Jacobian clamps the projected mean to this many half image sizes
                                             # around the image centre (the reference's 1.3 tan(half fov))
    dilation: float = 0.3                    # low-pass filter added to the diagonal of the 2D covariance
    alpha_min: float = 1.0 / 255.0           # skip a Gaussian whose alpha is below this
    alpha_max: float = 0.99                  # clamp alpha
    transmittance_min: float = 1e-4          # stop before a Gaussian that would bring T below this
    antialiased: bool = False                # Mip-Splatting's 2D filter (gsplat's "antialiased" mode, the 2024
                                             # reference's --antialiasing): opacity times sqrt(det(S) / det(S + 0.3 I))
    footprint: str = "ellipse"               # FOOTPRINTS: blend a Gaussian only in the tiles its alpha >= alpha_min
                                             # ellipse reaches ('ellipse'), or in every tile of the ellipse's bounding
                                             # box ('box'; the reference: a 3-sigma square); the same image and
                                             # gradients, less work
    lanes: str = "balanced"                  # LANES: training picks the blend's layout by the tiles' load and the
                                             # Gaussians' size ('balanced') or keeps the backend's one ('fixed')


@dataclass(frozen=True)
class OptimConfig:
    """Adam and the loss (3DGS defaults, 30k iterations)."""

    iterations: int = 30_000
    position_lr_init: float = 1.6e-4         # times the scene extent
    position_lr_final: float = 1.6e-6        # times the scene extent
    position_lr_delay_steps: int = 0         # ramp the position rate up from delay_mult times its value over this many
    position_lr_delay_mult: float = 0.01     # steps; the reference never passes its delay steps (0), so its 0.01 has
                                             # no effect by default
    position_lr_max_steps: int = 30_000
    feature_lr: float = 2.5e-3               # SH DC; the higher bands use feature_lr / 20
    opacity_lr: float = 0.05                 # the paper's value (the 2024 revision of the reference code uses 0.025)
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    adam_eps: float = 1e-15
    lambda_dssim: float = 0.2                # loss = (1 - lambda) L1 + lambda (1 - SSIM)
    ssim_padding: str = "same"               # SSIM_PADDINGS: the reference's mean over every pixel ('same') or
                                             # gsplat's over the pixels whose window lies inside the image ('valid')
    sh_degree: int = 3                       # maximum SH degree
    sh_increase_interval: int = 1000         # the active degree goes up by one every this many iterations
    random_background: bool = False          # a random background colour per iteration
    coarse_to_fine: str = "off"              # COARSE_TO_FINE: render and fit the training images at a reduced
                                             # resolution early, rising to full by coarse_until ('spectrum':
                                             # DashGaussian's schedule from the images' spectra)
    coarse_until: int = 0                    # ... the iteration where it reaches full resolution (0: the end of
                                             # densification, densify.densify_until_iter, as DashGaussian)
    alpha_weight: float = 0.0                # images with alpha (an object on an empty background): loss +=
                                             # alpha_weight * L1(rendered alpha, the image's alpha), so that a
                                             # Gaussian of the background's colour in empty space is not free
    row_order: str = "spatial"               # ROW_ORDERS: the model's rows sorted by where the Gaussians are (a Morton
                                             # code of their means) at the start and after each refinement, or kept in
                                             # the order densification makes them ('creation', the reference's)
    step_on_refine: bool = False             # also take the Adam step on the iterations that densify or reset
                                             # opacities, before the refinement (gsplat's order); false: the
                                             # reference's, whose rebuilt parameters have no gradient there
    depth_weight: float = 0.0                # Mitsuba scenes: weight of the inverse-depth L1 against exact depth
    depth_weight_final: float = 0.0          # ... decaying exponentially to this over position_lr_max_steps (--depth-weight W:
                                             # W to W / DEPTH_WEIGHT_DECAY, the 2024 reference's 1.0 to 0.01)
    exposure: str = "off"                    # --exposure: 'affine', a 3x4 colour transform per training image before
                                             # the loss (EXPOSURES; optim/exposure.py), or 'bilateral', a grid of
                                             # them (optim/bilateral.py)
    exposure_lr_init: float = 0.01           # affine: its Adam's rate, decaying exponentially over the run's
    exposure_lr_final: float = 0.001         # iterations to this (the 2024 reference's values)
    exposure_grid: tuple[int, int, int] = (16, 16, 8)   # bilateral: cells along x, y and the guidance (gsplat's)
    exposure_grid_lr: float = 2e-3           # bilateral: its Adam's rate (gsplat's: warmed up over 1,000 steps,
                                             # then decaying to 1 % over the run's iterations)
    exposure_grid_tv: float = 10.0           # bilateral: weight of the grids' total variation (gsplat's)
    pose_opt: bool = False                   # --pose-opt: learn a rigid correction of every training camera
                                             # (optim/pose.py, gsplat's pose_opt)
    pose_opt_lr: float = 1e-4                # its Adam's rate at the start: 10x gsplat's 1e-5, since ours is sparse
                                             # (a camera steps only where it is rendered); measured, README
    pose_opt_lr_decay: float = 1.0           # ... moving exponentially to this factor times it over
                                             # position_lr_max_steps (1: constant, as gsplat's; < 1 decays, > 1
                                             # grows)
    pose_opt_reg: float = 1e-6               # its L2 weight decay (gsplat's pose_opt_reg)
    pose_opt_pivot: str = "centre"           # where a correction's rotation turns a camera: "centre" (its own centre,
                                             # gsplat's) or "depth" (a point ahead at the depth of the scene points it
                                             # sees, pose.pivot_depths: rotation and translation then separate)

    def with_depth_weight(self, weight: float) -> "OptimConfig":
        """Depth supervision of weight ``weight`` decaying to ``weight / DEPTH_WEIGHT_DECAY`` (``--depth-weight``)."""
        return dataclasses.replace(self, depth_weight=weight, depth_weight_final=weight / DEPTH_WEIGHT_DECAY)


@dataclass(frozen=True)
class DensifyConfig:
    """Adaptive density control (reference behaviour; docs/conventions.md)."""

    densify_from_iter: int = 500
    densify_until_iter: int = 15_000
    densification_interval: int = 100
    opacity_reset_interval: int = 3000       # opacity reset every this many iterations while densifying (and, on a
                                             # white background, at densify_from_iter, as the reference); 0: never
    grad_threshold: float = 2e-4             # mean NDC-space norm of dL/d(projected mean)
    absgrad: bool = False                    # AbsGS / gsplat's absgrad: the statistic sums |per-pixel gradient|
    absgrad_threshold: float = 8e-4          # grad_threshold in absgrad mode (gsplat's advice for absgrad)
    percent_dense: float = 0.01              # clone when max scale <= percent_dense * extent, else split
    split_count: int = 2                     # a split Gaussian becomes this many
    split_scale_divisor: float = 1.6         # (0.8 * split_count) in the reference
    min_opacity: float = 0.005               # prune below this opacity
    prune_large_after: int = 3000            # after this iteration also prune the Gaussians that are too large:
    max_world_scale: float = 0.1             # max world scale above this times the extent, or
    max_screen_fraction: float = 0.0         # max 2D radius above this fraction of max(width, height) in any view since
                                             # the last densification (gsplat's prune_scale2d, 0.15 when it is on);
                                             # 0: off, the reference's effective rule (its 20 px test never fires)
                                             # -- except on an empty background, see empty_screen_fraction
    screen_prune_span: int = 500             # ... only in the densifications of this many iterations after
                                             # prune_large_after (gsplat's refine_scale2d_stop_iter, as a span);
                                             # 0: in every one until densify_until_iter
    empty_background: str = "auto"           # an object on an empty background (EMPTY_BACKGROUNDS): 'auto' when a
                                             # training image has transparent pixels (alpha, a mask), 'on', 'off'
                                             # (the reference). There the floaters of the random initial points
                                             # show: an opacity reset at densify_from_iter on any background (the
                                             # reference: on white only), and the screen-size prune at
                                             # empty_screen_fraction when max_screen_fraction is 0
    empty_screen_fraction: float = 0.1       # (the reference's 20 px of a 200-pixel image, relative); 0: no prune
    weight_prune: float = 0.0                # at densify_until_iter, remove the Gaussians whose largest blending
                                             # weight in a training view (the sum over its pixels of T * alpha, as a
                                             # share of the view's pixels: optim/weights.py) is below this; 0: off
                                             # (the reference)
    prune_unseen: bool = False               # at densify_until_iter, remove the Gaussians no training view shows:
                                             # blending weight below raster.alpha_min (the renderer's cut-off) of
                                             # one pixel in every training view; false: keep them (the reference;
                                             # on the CLI's 7k schedule they are 3 % of the model and their
                                             # removal saves less than the weights cost; docs/benchmarks/
                                             # work_per_step.md)
    error_gate: float = 0.0                  # densify only the candidates whose error score (their blending
                                             # weight in the high-error pixels of error_views sampled training views,
                                             # optim/weights.py error_weights) is at least this many times the
                                             # model's mean score (FastGS's multi-view consistent densification);
                                             # 0: off (the reference)
    error_views: int = 10                    # views sampled for error_gate at each densification (FastGS: 10)
    error_threshold: float = 0.1             # a pixel is high-error above this share of its view's error range
    reset_opacity: float = 0.01              # opacity reset: opacity = min(opacity, reset_opacity)
    reset_once: bool = False                 # a reset goes only over the Gaussians no reset has gone over yet (rows
                                             # created since the previous reset, and the initial points at the
                                             # first); false: over every Gaussian at every reset, the reference


@dataclass(frozen=True)
class MCMCConfig:
    """MCMC densification (Kheradmand et al. 2024, "3D Gaussian Splatting as Markov Chain Monte Carlo"), gsplat's
    ``MCMCStrategy`` defaults; used with ``TrainConfig.strategy = "mcmc"`` (``--strategy mcmc``)."""

    cap_max: int = 1_000_000                 # --max-gaussians: the number of Gaussians never exceeds this
    refine_start_iter: int = 500             # relocate and grow when refine_start < step < refine_stop ...
    refine_stop_iter: int = 25_000
    refine_every: int = 100                  # ... and step % refine_every == 0
    growth: float = 0.05                     # each refinement adds this fraction of the count (up to cap_max)
    min_opacity: float = 0.005               # Gaussians at or below this opacity are dead and get relocated
    noise_lr: float = 5e5                    # position noise: noise_lr times the position learning rate
    opacity_reg: float = 0.01                # loss += opacity_reg * mean(opacity)
    scale_reg: float = 0.01                  # loss += scale_reg * mean(exp(scales))
    init_opacity: float = 0.5                # initial opacity (the paper's strategy: 0.1)
    init_scale: float = 0.1                  # initial scale factor on the nearest-neighbour distance (paper: 1)


@dataclass(frozen=True)
class SceneConfig:
    """``mi-gs optimize scene.xml``: how a Mitsuba scene becomes training views (``mi_gaussians.data.scene_dataset``).

    ``None`` means "from the scene's own (first) sensor", falling back to the value in the comment."""

    defines: tuple[str, ...] = ()            # "KEY=VALUE" scene parameters (Mitsuba's -D: <default name="KEY">)
    rig: str = "auto"                        # 'auto' (the scene's sensors if it declares several, else
                                             # 'hemisphere'), 'sensors', 'hemisphere' or 'sphere'
    views: int = 64                          # generated training cameras
    test_views: int = 8                      # generated held-out cameras (declared sensors: every test_every-th)
    resolution: tuple[int, ...] | None = None   # film size (width[, height]: a width alone keeps the sensor's
                                             # aspect); fallback 256 x 256
    fov: float | None = None                 # horizontal field of view in degrees; fallback 40
    radius: float | None = None              # rig radius; None: the bounding sphere fills the view
    up: tuple[float, float, float] | None = None  # world up; None: the sensor's up snapped to an axis, else +Y
    elevation: tuple[float, float] = (10.0, 75.0)  # hemisphere rig: camera elevation range in degrees
    spp: int | None = None                   # reference samples per pixel; fallback 128
    linear: bool = False                     # train on linear radiance (default: on the sRGB-encoded references)
    init: str = "shapes"                     # 'shapes' (Mitsuba shape sampling, coloured by the references),
                                             # 'random' (uniform in the bounding box), 'triangulate' (SIFT points
                                             # triangulated from the references with the scene's exact cameras) or
                                             # 'sfm' (pycolmap structure from motion, poses found again)
    init_points: int = 50_000                # points to sample ('shapes', 'random')


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs; saved with its outputs (``config.json``) and read back by ``--resume``."""

    data: DataConfig = DataConfig()
    optim: OptimConfig = OptimConfig()
    densify: DensifyConfig = DensifyConfig()
    raster: RasterConfig = RasterConfig()
    scene: SceneConfig = SceneConfig()       # used only when the input is a Mitsuba scene file
    triangulate: TriangulateConfig = TriangulateConfig()   # used when data.init triangulates
    strategy: str = "default"                # densification: a name of STRATEGIES ('default': the paper's, 'mcmc')
    mcmc: MCMCConfig = MCMCConfig()
    seed: int = 0
    checkpoint_every: int = 1000             # iterations between checkpoints (and the last iteration)
    eval_every: int = 1000                   # iterations between test-set evaluations for the curves (0: only at the end)
    save_iterations: tuple[int, ...] = (7_000, 30_000)   # also write point_cloud_<iter>.ply at these iterations
    freeze: bool = True                      # record the training step once and replay it (dr.freeze, no host sync
                                             # per iteration); false: trace every iteration (same results, slower)
    row_classes: int = 0                     # > 0: frozen steps run on the model padded with inert rows to a size
                                             # class, this many classes per doubling (one recording per class, not
                                             # per size; optim/train_step.py); 0: at its own size, one recording per
                                             # densification (measured faster on the CPU: README, "Performance")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    # Fields that existed in earlier versions and were removed; a saved config.json that still names them loads (the
    # values are ignored). tile_size had no effect; densify.max_screen_size (pixels) was a rule stated in pixels, which
    # pruned twice the share of a 400-pixel image as of a 200-pixel one: densify.max_screen_fraction replaces it,
    # relative to the image (a run recorded with it resumes under the new rule).
    RETIRED = {"RasterConfig": ("tile_size",), "DataConfig": ("random_init",),   # (random_init: now data.init)
               "DensifyConfig": ("max_screen_size",)}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The configuration a run saved (``config.json``'s ``"train"``, JSON values): every field's type and range
        checked (:class:`SettingError` naming the key, e.g. ``optim.iterations``); missing fields take their
        defaults, unknown ones are refused."""
        dens = d.get("densify") if isinstance(d, dict) else None
        if isinstance(dens, dict) and "opacity_reset_interval" in dens and "prune_large_after" not in dens:
            # (a record from before prune_large_after: its large-Gaussian prunes began after the first reset)
            d = {**d, "densify": {**dens, "prune_large_after": dens["opacity_reset_interval"]}}
        if isinstance(dens, dict) and "opacity_reset_interval" in dens and "empty_background" not in dens:
            # (a record from before the empty-background rules: it trained without them, and its screen-size prune,
            # when it had one, pruned in every densification)
            d = {**d, "densify": {**d["densify"], "empty_background": "off",
                                  "screen_prune_span": dens.get("screen_prune_span", 0)}}
        data = d.get("data") if isinstance(d, dict) else None
        if isinstance(data, dict) and "extent" not in data:
            # (a record from before data.extent: its lengths were fractions of the cameras' spread)
            d = {**d, "data": {**data, "extent": "cameras"}}
        return _from_json(cls, d, "").validate()

    def with_settings(self, assignments) -> "TrainConfig":
        """A copy with ``"section.field=value"`` (or ``"field=value"`` for top-level fields) assignments applied,
        each value parsed as its field's type and checked against :data:`RULES`: ``--set densify.min_opacity=0.1
        --set data.background=1,1,1``. Raises :class:`SettingError` (a ValueError) with a one-line message for an
        unknown name, a value of the wrong type or out of range."""
        import typing

        sections = _sections(self)
        cfg = self
        for text in assignments:
            key, sep, value = str(text).partition("=")
            key = key.strip()
            if not sep or not key:
                raise ValueError(f"setting {text!r}: expected NAME=VALUE, e.g. densify.min_opacity=0.1")
            path = key.split(".")
            if len(path) > 2:
                raise SettingError(key, "expected SECTION.FIELD or FIELD")
            if len(path) == 2 and path[0] not in sections:
                raise SettingError(key, f"no section {path[0]!r} (sections: {', '.join(sections)})")
            if len(path) == 1 and key in sections:
                raise SettingError(key, f"{key} is a section, set one of its fields ({key}.FIELD=VALUE)")
            owner, name = (cfg, key) if len(path) == 1 else (getattr(cfg, path[0]), path[1])
            fields = [f.name for f in dataclasses.fields(owner) if f.name not in sections]
            if name not in fields:
                raise SettingError(key, f"no such field (fields{' of ' + path[0] if len(path) == 2 else ''}: "
                                        f"{', '.join(fields)})")
            parsed = parse_value(typing.get_type_hints(type(owner))[name], value.strip(), key)
            _check_value(key, parsed)
            owner = dataclasses.replace(owner, **{name: parsed})
            cfg = owner if len(path) == 1 else dataclasses.replace(cfg, **{path[0]: owner})
        return cfg

    def with_iterations(self, n: int) -> "TrainConfig":
        """A run of ``n`` iterations with the paper's proportions: the position schedule spans the run, a shorter
        run densifies until half of it (15k of 30k) and refines MCMC until 5/6 of it (25k of 30k), and models are
        saved only at iterations before its end."""
        shorter = n < OptimConfig().iterations
        return dataclasses.replace(
            self, optim=dataclasses.replace(self.optim, iterations=n, position_lr_max_steps=n),
            densify=dataclasses.replace(self.densify, densify_until_iter=min(self.densify.densify_until_iter, n // 2))
            if shorter else self.densify,
            mcmc=dataclasses.replace(self.mcmc, refine_stop_iter=min(self.mcmc.refine_stop_iter, n * 5 // 6))
            if shorter else self.mcmc,
            save_iterations=tuple(i for i in self.save_iterations if i < n))

    def validate(self) -> "TrainConfig":
        """``self`` when every setting lies in its range (:data:`RULES`; other numbers >= 0), else
        :class:`SettingError` naming the first that does not."""
        for key, value in setting_items(self):
            _check_value(key, value)
        return self

    def check(self, scene_file: bool, given=()) -> "TrainConfig":
        """:meth:`validate`, and the rules between settings and the input, for a new run: depth supervision needs
        the exact depth of a Mitsuba scene (``scene_file``) and a final weight; ``given`` (the keys the user set)
        must not hold a setting of a strategy the run does not use (it would be silently ignored)."""
        self.validate()
        if self.optim.depth_weight > 0 and not scene_file:
            raise SettingError("optim.depth_weight", "needs the exact depth of a Mitsuba scene: give a scene .xml")
        if self.optim.depth_weight > 0 and not self.optim.depth_weight_final > 0:
            raise SettingError("optim.depth_weight_final", "must be > 0 with optim.depth_weight (the weight decays "
                                                           "exponentially to it; --depth-weight W sets W and "
                                                           f"W/{DEPTH_WEIGHT_DECAY:g})")
        own = STRATEGIES[self.strategy]
        for key in given:
            section = key.partition(".")[0]
            if section in STRATEGIES.values() and section != own:
                other = next(name for name, s in STRATEGIES.items() if s == section)
                raise SettingError(key, f"the {section} section configures --strategy {other}, not the "
                                        f"{self.strategy} strategy of this run")
        return self


# ------------------------------------------------------------------------------------------------------ the rules
@dataclass(frozen=True)
class Range:
    """Numbers (or each number of a tuple) in [low, high]; ``open_low`` / ``open_high`` exclude an end; ``counts``:
    how many numbers a tuple may hold (at least, at most)."""

    low: float | None = None
    high: float | None = None
    open_low: bool = False
    open_high: bool = False
    counts: tuple[int, int] | None = None

    def allows(self, v: float) -> bool:
        return ((self.low is None or (v > self.low if self.open_low else v >= self.low))
                and (self.high is None or (v < self.high if self.open_high else v <= self.high)))

    def __str__(self) -> str:
        lo = None if self.low is None else f"{'>' if self.open_low else '>='} {self.low:g}"
        hi = None if self.high is None else f"{'<' if self.open_high else '<='} {self.high:g}"
        return "must be " + " and ".join(t for t in (lo, hi) if t)


_COUNT = Range(1)                               # iterations, intervals, counts
_POSITIVE = Range(0, open_low=True)
_FRACTION = Range(0, 1)
_OPEN_FRACTION = Range(0, 1, open_low=True, open_high=True)

#: What each setting may be, by ``section.field`` (a Range, or a tuple of the names it may take). A number not
#: listed must be >= 0; tuples not listed are free (an up vector may point down).
RULES: dict[str, "Range | tuple[str, ...]"] = {
    "strategy": tuple(STRATEGIES), "checkpoint_every": _COUNT,
    "data.resolution": _COUNT, "data.random_points": _COUNT, "data.init": INITS, "data.extent": EXTENTS,
    "data.background": Range(0), "data.pose_noise": Range(0, counts=(2, 2)),
    "optim.iterations": _COUNT, "optim.position_lr_max_steps": _COUNT, "optim.sh_degree": Range(0, 3),
    "optim.sh_increase_interval": _COUNT, "optim.lambda_dssim": _FRACTION, "optim.adam_eps": _POSITIVE,
    "optim.pose_opt_lr_decay": Range(0, 100, open_low=True), "optim.pose_opt_pivot": POSE_PIVOTS,
    # Adam's rates: about the size of a step, in each group's own units (the position's in scene extents, a pose
    # correction's in radians and extents); larger ones diverge or throw the quantity around at once
    **{f"optim.{name}": Range(0, 1) for name in ("position_lr_init", "position_lr_final", "feature_lr", "opacity_lr",
                                                 "scaling_lr", "rotation_lr", "exposure_lr_init", "exposure_lr_final",
                                                 "exposure_grid_lr")},
    "optim.pose_opt_lr": Range(0, 0.1),
    "optim.coarse_to_fine": COARSE_TO_FINE, "optim.row_order": ROW_ORDERS, "optim.exposure": EXPOSURES, "optim.ssim_padding": SSIM_PADDINGS, "optim.exposure_grid": Range(2, counts=(3, 3)),
    "densify.densification_interval": _COUNT, "densify.split_count": _COUNT,
    "densify.split_scale_divisor": _POSITIVE, "densify.min_opacity": Range(0, 1, open_high=True),
    "densify.reset_opacity": _OPEN_FRACTION, "densify.weight_prune": Range(0, 1),
    "densify.error_gate": Range(0), "densify.error_views": _COUNT, "densify.error_threshold": Range(0, 1, open_high=True),
    "densify.empty_background": EMPTY_BACKGROUNDS, "densify.empty_screen_fraction": Range(0, 1),
    "raster.footprint": FOOTPRINTS, "raster.lanes": LANES, "raster.near_plane": _POSITIVE, "raster.guard_band": _POSITIVE, "raster.alpha_min": _OPEN_FRACTION,
    "raster.alpha_max": Range(0, 1, open_low=True), "raster.transmittance_min": Range(0, 1, open_high=True),
    "mcmc.cap_max": _COUNT, "mcmc.refine_every": _COUNT, "mcmc.min_opacity": Range(0, 1, open_high=True),
    "mcmc.init_opacity": _OPEN_FRACTION, "mcmc.init_scale": _POSITIVE,
    "scene.rig": RIGS, "scene.views": _COUNT, "scene.resolution": Range(16, counts=(1, 2)),
    "scene.fov": Range(0, 180, open_low=True, open_high=True),
    "scene.radius": _POSITIVE, "scene.elevation": Range(-90, 90), "scene.spp": _COUNT, "scene.init": SCENE_INITS,
    "scene.init_points": _COUNT,
    "triangulate.neighbours": _COUNT, "triangulate.max_features": _COUNT, "triangulate.min_track_length": Range(2),
    "triangulate.min_points": _COUNT,
}


def check_section(section: str, values) -> None:
    """:class:`SettingError` for the first field of one section (e.g. ``"mcmc"``, an :class:`MCMCConfig`) outside
    its rule: for code that takes a section alone (a strategy)."""
    for key, value in setting_items(values, section + "."):
        _check_value(key, value)


def _check_value(key: str, value) -> None:
    rule = RULES.get(key)
    if isinstance(rule, tuple):
        if value not in rule:
            raise SettingError(key, f"{value!r} is not one of {', '.join(rule)}")
        return
    items = value if isinstance(value, tuple) else (value,)
    if isinstance(value, tuple) and rule is None:
        return
    if isinstance(value, tuple) and rule.counts and not rule.counts[0] <= len(value) <= rule.counts[1]:
        raise SettingError(key, f"expected {rule.counts[0]} to {rule.counts[1]} values, got {len(value)}")
    for v in items:
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not (rule or Range(0)).allows(v):
            if rule is None:
                raise SettingError(key, f"must not be negative, got {v}")
            raise SettingError(key, f"{rule}, got {v}")


def _sections(cfg) -> list[str]:
    return [f.name for f in dataclasses.fields(cfg) if dataclasses.is_dataclass(getattr(cfg, f.name))]


def setting_items(cfg, prefix: str = ""):
    """(``section.field``, value) for every setting of ``cfg`` (a TrainConfig, or a section with ``prefix``)."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            yield from setting_items(value, f"{prefix}{f.name}.")
        else:
            yield prefix + f.name, value


# ------------------------------------------------------------------------------------------- reading values
def _from_json(kind, values, prefix: str):
    """An instance of the dataclass ``kind`` from JSON ``values`` (types checked, defaults for missing fields)."""
    import typing

    section = prefix.rstrip(".") or "the training settings"
    if not isinstance(values, dict):
        raise SettingError(section, f"expected an object of settings, got {shown(values)}")
    names = {f.name: f for f in dataclasses.fields(kind)}
    hints = typing.get_type_hints(kind)
    retired = TrainConfig.RETIRED.get(kind.__name__, ())
    kw = {}
    for k, v in values.items():
        if k in retired:
            continue
        if k not in names:
            raise SettingError(prefix + str(k), f"unknown setting (known in {section}: {', '.join(names)})")
        default = names[k].default
        if dataclasses.is_dataclass(default):
            kw[k] = _from_json(type(default), v, f"{prefix}{k}.")
        else:
            kw[k] = json_value(hints[k], v, prefix + k)
    return kind(**kw)
