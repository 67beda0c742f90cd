"""Every default of mi-gaussians, in frozen dataclasses (the only home of defaults: the command line reads them).

Values follow the 3DGS paper and its reference implementation (see ``conventions.md``); where we differ on purpose,
the field's comment says so.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DataConfig:
    resolution: int = 1                      # -r: divide the image size by 1, 2, 4 or 8 (images_N folders when present)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # RGBA images are composited over this colour
    test_every: int = 8                      # COLMAP / single-transforms layouts: index % test_every == 0 is test (0: no test split)
    random_points: int = 100_000             # initial points for layouts without SfM points
    random_init: str = "cube"                # ... sampled in the reference's cube, or 'frustum': where the training
                                             # cameras look (data/pointcloud.py)
    masks: bool = True                       # COLMAP layout: composite each image over the background through its
                                             # mask in masks/ (white = object) when that folder exists
    seed: int = 0


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
    sh_degree: int = 3                       # maximum SH degree
    sh_increase_interval: int = 1000         # the active degree goes up by one every this many iterations
    random_background: bool = False          # a random background colour per iteration
    depth_weight: float = 0.0                # Mitsuba scenes: weight of the inverse-depth L1 against exact depth
    depth_weight_final: float = 0.0          # ... decaying exponentially to this over position_lr_max_steps (--depth-weight W:
                                             # W to W / 100, the 2024 reference's 1.0 to 0.01)


@dataclass(frozen=True)
class DensifyConfig:
    """Adaptive density control (reference behaviour; see conventions.md)."""

    densify_from_iter: int = 500
    densify_until_iter: int = 15_000
    densification_interval: int = 100
    opacity_reset_interval: int = 3000
    grad_threshold: float = 2e-4             # mean NDC-space norm of dL/d(projected mean)
    absgrad: bool = False                    # AbsGS / gsplat's absgrad: the statistic sums |per-pixel gradient|
    absgrad_threshold: float = 8e-4          # grad_threshold in absgrad mode (gsplat's advice for absgrad)
    percent_dense: float = 0.01              # clone when max scale <= percent_dense * extent, else split
    split_count: int = 2                     # a split Gaussian becomes this many
    split_scale_divisor: float = 1.6         # (0.8 * split_count) in the reference
    min_opacity: float = 0.005               # prune below this opacity
    max_screen_size: float = 20.0            # after the first opacity reset, prune max 2D radius above this (px)
    max_world_scale: float = 0.1             # ... or max world scale above this times the extent
    reset_opacity: float = 0.01              # opacity reset: opacity = min(opacity, reset_opacity)


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
    resolution: tuple[int, int] | None = None   # film size (width, height); fallback 256 x 256
    fov: float | None = None                 # horizontal field of view in degrees; fallback 40
    radius: float | None = None              # rig radius; None: the bounding sphere fills the view
    up: tuple[float, float, float] | None = None  # world up; None: the sensor's up snapped to an axis, else +Y
    elevation: tuple[float, float] = (10.0, 75.0)  # hemisphere rig: camera elevation range in degrees
    spp: int | None = None                   # reference samples per pixel; fallback 128
    linear: bool = False                     # train on linear radiance (default: on the sRGB-encoded references)
    init: str = "shapes"                     # 'shapes' (Mitsuba shape sampling, coloured by the references),
                                             # 'random' (uniform in the bounding box) or 'sfm' (pycolmap)
    init_points: int = 50_000                # points to sample ('shapes', 'random')


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs; saved with its outputs (``config.json``) and read back by ``--resume``."""

    data: DataConfig = DataConfig()
    optim: OptimConfig = OptimConfig()
    densify: DensifyConfig = DensifyConfig()
    raster: RasterConfig = RasterConfig()
    scene: SceneConfig = SceneConfig()       # used only when the input is a Mitsuba scene file
    strategy: str = "default"                # densification: 'default' (the paper's, ``densify``) or 'mcmc' (``mcmc``)
    mcmc: MCMCConfig = MCMCConfig()
    seed: int = 0
    checkpoint_every: int = 1000             # iterations between checkpoints (and the last iteration)
    eval_every: int = 1000                   # iterations between test-set evaluations for the curves (0: only at the end)
    save_iterations: tuple[int, ...] = (7_000, 30_000)   # also write point_cloud_<iter>.ply at these iterations
    freeze: bool = True                      # record the training step once and replay it (dr.freeze, no host sync
                                             # per iteration); false: trace every iteration (same results, slower)

    def to_dict(self) -> dict:
        import dataclasses

        return dataclasses.asdict(self)

    # Fields that existed in earlier versions and were removed because they had no effect; a saved config.json that
    # still names them loads (the values are ignored).
    RETIRED = {"RasterConfig": ("tile_size",)}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        import dataclasses

        def build(kind, values):
            names = {f.name: f for f in dataclasses.fields(kind)}
            values = {k: v for k, v in values.items() if k not in cls.RETIRED.get(kind.__name__, ())}
            unknown = set(values) - set(names)
            if unknown:
                raise ValueError(f"unknown {kind.__name__} setting(s): {', '.join(sorted(unknown))}")
            kw = {}
            for k, v in values.items():
                default = getattr(kind(), k)
                if dataclasses.is_dataclass(default):
                    kw[k] = build(type(default), v)
                elif isinstance(default, tuple) or isinstance(v, list):   # (JSON gives lists)
                    kw[k] = None if v is None else tuple(v)
                else:
                    kw[k] = v
            return kind(**kw)

        return build(cls, d)

    def with_settings(self, assignments) -> "TrainConfig":
        """A copy with ``"section.field=value"`` (or ``"field=value"`` for top-level fields) assignments applied,
        each value parsed as its field's type: ``--set densify.min_opacity=0.1 --set data.background=1,1,1``.
        Raises ValueError with a one-line message for an unknown name or a value of the wrong type."""
        import dataclasses

        import typing

        sections = [f.name for f in dataclasses.fields(self) if dataclasses.is_dataclass(getattr(self, f.name))]
        cfg = self
        for text in assignments:
            key, sep, value = str(text).partition("=")
            key = key.strip()
            if not sep or not key:
                raise ValueError(f"setting {text!r}: expected NAME=VALUE, e.g. densify.min_opacity=0.1")
            path = key.split(".")
            if len(path) > 2:
                raise ValueError(f"setting {key!r}: expected SECTION.FIELD or FIELD")
            if len(path) == 2 and path[0] not in sections:
                raise ValueError(f"setting {key!r}: no section {path[0]!r} (sections: {', '.join(sections)})")
            if len(path) == 1 and key in sections:
                raise ValueError(f"setting {key!r}: {key} is a section, set one of its fields ({key}.FIELD=VALUE)")
            owner, name = (cfg, key) if len(path) == 1 else (getattr(cfg, path[0]), path[1])
            fields = [f.name for f in dataclasses.fields(owner) if f.name not in sections]
            if name not in fields:
                raise ValueError(f"setting {key!r}: no such field (fields{' of ' + path[0] if len(path) == 2 else ''}:"
                                 f" {', '.join(fields)})")
            parsed = _parse_value(typing.get_type_hints(type(owner))[name], value.strip(), key)
            if isinstance(parsed, (int, float)) and not isinstance(parsed, bool) and parsed < 0:
                raise ValueError(f"setting {key!r}: must not be negative, got {parsed}")
            owner = dataclasses.replace(owner, **{name: parsed})
            cfg = owner if len(path) == 1 else dataclasses.replace(cfg, **{path[0]: owner})
        return cfg


def _parse_value(kind, text: str, key: str):
    """``text`` as a value of the type ``kind`` (bool, int, float, str, tuples of those, optionally ``| None``)."""
    import types
    import typing

    args = typing.get_args(kind)
    if isinstance(kind, types.UnionType) or typing.get_origin(kind) is typing.Union:
        if text.lower() == "none" and type(None) in args:
            return None
        (kind,) = [a for a in args if a is not type(None)]
        args = typing.get_args(kind)
    if typing.get_origin(kind) is tuple:
        items = [t for t in text.replace(",", " ").split() if t]
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_parse_value(args[0], t, key) for t in items)
        if len(items) != len(args):
            raise ValueError(f"setting {key!r}: expected {len(args)} comma-separated values, got {text!r}")
        return tuple(_parse_value(a, t, key) for a, t in zip(args, items))
    try:
        if kind is bool:
            low = text.lower()
            if low not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return low in ("true", "1", "yes")
        if kind is int:
            return int(text.replace("_", ""))
        if kind is float:
            value = float(text)
            if value != value or value in (float("inf"), float("-inf")):
                raise ValueError
            return value
        if kind is str:
            return text
    except ValueError:
        raise ValueError(f"setting {key!r}: {text!r} is not a valid {kind.__name__}") from None
    raise ValueError(f"setting {key!r}: values of type {kind} cannot be set from the command line")
