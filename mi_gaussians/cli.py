"""``mi-gs``: the command-line interface. Arguments -> config dataclasses -> library calls.

Every subcommand selects the Mitsuba variant first (``--variant``; default ``cuda_ad_rgb`` when a CUDA device is
present, else ``llvm_ad_rgb``). Errors in the user's input print one line, ``mi-gs: error: <file>: <problem>``, and
exit with status 2; nothing is half-written (all outputs are written atomically).
"""

from __future__ import annotations

import argparse
import errno
import json
import math
import sys
from pathlib import Path

EXIT_INPUT_ERROR = 2


class InputError(Exception):
    """A problem with the user's input, reported as one line."""


# The rasterizer is Dr.Jit code with a hand-written backward pass and RGB colours: a JIT variant with automatic
# differentiation and RGB colour
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")


def _default_variant() -> str:
    import drjit as dr

    return "cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb"


def _set_variant(name: str | None) -> None:
    import drjit as dr
    import mitsuba as mi

    variant = name or _default_variant()
    if variant not in SUPPORTED_VARIANTS:
        known = "a Mitsuba variant mi-gs cannot use" if variant in mi.variants() else "not a Mitsuba variant"
        raise InputError(f"--variant {variant}: {known} (mi-gs runs on {' or '.join(SUPPORTED_VARIANTS)})")
    if variant.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
        raise InputError(f"--variant {variant}: no CUDA device or driver is available on this machine "
                         "(use llvm_ad_rgb)")
    mi.set_variant(variant)


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def finite_float(text: str) -> float:
    """argparse type: a finite number (no nan or inf)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text}")
    return value


def field_of_view(text: str) -> float:
    """argparse type: a field of view in degrees, strictly between 0 and 180."""
    value = finite_float(text)
    if not 0 < value < 180:
        raise argparse.ArgumentTypeError(f"expected degrees between 0 and 180, got {text}")
    return value


def sh_degree(text: str) -> int:
    """argparse type: a spherical-harmonics degree 0..3."""
    value = _integer(text)
    if not 0 <= value <= 3:
        raise argparse.ArgumentTypeError(f"expected an SH degree 0, 1, 2 or 3, got {text}")
    return value


def _background(values) -> tuple[float, float, float]:
    if values is None:
        return (0.0, 0.0, 0.0)
    if len(values) == 1:
        return (values[0],) * 3
    if len(values) != 3:
        raise InputError("--background takes one value or three (r g b)")
    return tuple(values)


# ------------------------------------------------------------------------------------------------------ info
def _ply_info(path: Path) -> dict:
    import numpy as np

    from .conventions import sh_degree_from_coeff_count, sigmoid
    from .model.ply import read_ply

    p = read_ply(path)
    n = p["means"].shape[0]
    info = {"file": str(path), "gaussians": n, "sh_degree": sh_degree_from_coeff_count(p["sh_rest"].shape[1] + 1)}
    if n:
        opac = sigmoid(p["opacities"].astype(np.float64))
        sig = np.exp(p["scales"].astype(np.float64)).max(axis=1)
        info.update(bbox_min=p["means"].min(0).round(4).tolist(), bbox_max=p["means"].max(0).round(4).tolist(),
                    opacity_mean=round(float(opac.mean()), 4),
                    sigma_max_median=float(np.median(sig)))
    return info


def _scene_info(path: Path, defines) -> dict:
    from .data.scene_file import load_file

    scene = load_file(path, defines)
    return {"file": str(path), "integrator": scene.integrator().class_name() if scene.integrator() else None,
            "sensors": [s.id() or s.class_name() for s in scene.sensors()],
            "shapes": len(scene.shapes()), "bbox": [list(scene.bbox().min), list(scene.bbox().max)]}


def _dataset_info(path: Path, resolution: int) -> dict:
    from .data.dataset import load_dataset, unreadable_images

    ds = load_dataset(path, resolution=resolution)
    unreadable = unreadable_images(ds.views, progress=sys.stderr.isatty())
    cam = ds.train[0].camera
    return {"dataset": str(path), "layout": ds.layout, "train_views": len(ds.train), "test_views": len(ds.test),
            "image_size": [cam.width, cam.height], "fx": round(cam.fx, 4), "fy": round(cam.fy, 4),
            "cx": round(cam.cx, 4), "cy": round(cam.cy, 4), "color_space": ds.color_space,
            "points": 0 if ds.points_xyz is None else int(ds.points_xyz.shape[0]),
            "extent": round(ds.extent, 6), "images_checked": len(ds.views), "unreadable_images": unreadable}


def cmd_info(args) -> int:
    path = Path(args.path)
    if not path.exists():
        raise InputError(f"{path}: not found")
    if path.suffix.lower() == ".ply":
        info = _ply_info(path)
    elif path.suffix.lower() == ".xml":
        info = _scene_info(path, args.define)
    else:
        info = _dataset_info(path, args.resolution)
    print(json.dumps(info, indent=2))
    bad = info.get("unreadable_images")
    if bad:
        sys.stdout.flush()
        raise InputError(f"{path}: {len(bad)} of {info['images_checked']} images cannot be read (listed above under "
                         f"unreadable_images), e.g. {bad[0]}")
    return 0


# ---------------------------------------------------------------------------------------------------- render
def _model_raster_config(ply: Path, antialiased: bool | None):
    """How to render ``ply``: as the run whose ``config.json`` sits beside it was trained (a PLY records nothing about
    anti-aliasing), unless ``--antialiased`` / ``--no-antialiased`` says otherwise; defaults for a lone model."""
    import dataclasses

    from . import run_folder
    from .config import RasterConfig

    cfg = RasterConfig()
    if ply.suffix.lower() == ".spz" and antialiased is None:      # (an .spz file records it)
        from .model.web_formats import read_model

        return dataclasses.replace(cfg, antialiased=bool(read_model(ply)[1]))
    if (ply.parent / run_folder.CONFIG).is_file():
        try:
            cfg = run_folder.saved_config(run_folder.read_saved(ply.parent, ""), ply.parent).raster
        except ValueError as e:      # e.g. another tool's config.json: not a run record
            if antialiased is None:
                print(f"mi-gs: warning: rendering with the default settings: {e}", file=sys.stderr)
    return cfg if antialiased is None else dataclasses.replace(cfg, antialiased=antialiased)


def _render_gaussians_views(args, views, color_space: str, out_paths) -> None:
    import numpy as np
    from tqdm import tqdm

    from .imwrite import write_image
    from .model.gaussians import Gaussians
    from .raster.rasterize import render

    g = Gaussians.load(args.input)
    bg = _background(args.background)
    cfg = _model_raster_config(Path(args.input), args.antialiased)
    for (name, cam), outs in tqdm(list(zip(views, out_paths)), desc="render", unit="view", disable=len(views) < 2):
        out = render(g, cam, background=bg, sh_degree=args.sh_degree, cfg=cfg)
        rgb = np.array(out.rgb, dtype=np.float32)
        if args.alpha:
            rgb = np.concatenate([rgb, np.array(out.alpha, dtype=np.float32)[..., None]], axis=-1)
        for p in outs:
            write_image(p, rgb, color_space)


def _outputs_for(path: Path) -> list[Path]:
    from .io_utils import check_output_file

    ext = path.suffix.lower()
    if ext not in (".exr", ".png"):
        raise InputError(f"{path}: unsupported output format {ext or '(none)'} (use .exr or .png)")
    check_output_file(path)
    return [path]


def _render_scene_file(args, src: Path, out: Path) -> int:
    """A Mitsuba scene .xml rendered by Mitsuba with its own integrator (linear outputs)."""
    import mitsuba as mi
    import numpy as np

    from .data.scene_file import load_file
    from .imwrite import write_image

    if args.antialiased is not None:
        raise InputError(f"--{'' if args.antialiased else 'no-'}antialiased applies to a .ply; in a scene .xml the "
                         "gaussian_splatting integrator's antialiased parameter decides")
    outputs = _outputs_for(out)
    scene = load_file(src, args.define)
    if not scene.sensors():
        raise InputError(f"{src}: the scene has no sensor")
    if args.sensor >= len(scene.sensors()):
        raise InputError(f"{src}: sensor index {args.sensor} out of range ({len(scene.sensors())} sensors)")
    img = np.array(mi.render(scene, sensor=args.sensor, spp=args.spp or 0), dtype=np.float32)
    for p in outputs:
        write_image(p, img[..., :4] if img.shape[-1] >= 4 else img[..., :3], "linear")
        print(p)
    return 0


def _render_dataset_views(args, out: Path) -> int:
    """A .ply rendered from the views of a dataset folder into the folder ``out`` (EXR and PNG per view)."""
    from .config import DataConfig
    from .data.dataset import load_dataset
    from .io_utils import check_output_folder

    ds = load_dataset(args.dataset, resolution=args.resolution or DataConfig().resolution,
                      background=_background(args.background))
    views = {"train": ds.train, "test": ds.test, "all": ds.views}[args.split]
    if not views:
        raise InputError(f"{args.dataset}: the {args.split} split is empty")
    if out.suffix:
        raise InputError(f"{out}: with --dataset, -o names an output folder")
    check_output_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [[out / f"{Path(v.name).stem}.exr", out / f"{Path(v.name).stem}.png"] for v in views]
    _render_gaussians_views(args, [(v.name, v.camera) for v in views], ds.color_space, paths)
    print(f"{len(views)} views -> {out}")
    return 0


def cmd_render(args) -> int:
    src = Path(args.input)
    if not src.exists():
        raise InputError(f"{src}: not found")
    out = Path(args.output)
    if src.suffix.lower() == ".xml":
        return _render_scene_file(args, src, out)
    if src.suffix.lower() not in MODEL_SUFFIXES:
        raise InputError(f"{src}: expected a model (.ply, .splat or .spz) or a Mitsuba scene .xml")
    if (args.camera is None) == (args.dataset is None):
        raise InputError("give exactly one of --camera CAM.json or --dataset DIR")
    if args.dataset is not None:
        return _render_dataset_views(args, out)
    if args.resolution is not None:
        raise InputError("-r/--resolution applies to --dataset only (with --camera, the camera JSON gives the "
                         "image size)")
    from .data.camera import Camera

    outputs = _outputs_for(out)
    cam = Camera.from_json(args.camera)
    _render_gaussians_views(args, [(cam.name or "view", cam)], args.color_space, [outputs])
    print(out)
    return 0


# ---------------------------------------------------------------------------------------------------- export
MODEL_SUFFIXES = (".ply", ".splat", ".spz")


def cmd_export(args) -> int:
    """A model (.ply, .splat or .spz) written in another of these formats, optionally with fewer SH bands."""
    import os

    from .io_utils import check_output_file
    from .model.web_formats import drop_sh_bands, read_model, write_model

    src, out = Path(args.input), Path(args.output)
    if not src.is_file():
        raise InputError(f"{src}: not found")
    if src.suffix.lower() not in MODEL_SUFFIXES:
        raise InputError(f"{src}: expected a model (.ply, .splat or .spz)")
    if out.suffix.lower() not in MODEL_SUFFIXES:
        raise InputError(f"{out}: unknown output format {out.suffix or '(none)'} (use .ply, .splat or .spz)")
    check_output_file(out)
    if out.exists() and not args.overwrite:
        raise InputError(f"{out}: exists (give --overwrite to replace it)")
    if out.exists() and out.resolve() == src.resolve():
        raise InputError(f"{out}: is the input model")
    params, _ = read_model(src)
    if args.sh_degree is not None:
        params = drop_sh_bands(params, args.sh_degree)
    if out.suffix.lower() == ".splat" and params["sh_rest"].shape[1]:
        print(f"mi-gs: note: .splat holds SH degree 0 only; the higher bands of {src} are dropped", file=sys.stderr)
    antialiased = _model_raster_config(src, args.antialiased).antialiased
    if antialiased and out.suffix.lower() != ".spz":
        print(f"mi-gs: note: {out.suffix} cannot record that {src} renders anti-aliased: render it with "
              "--antialiased", file=sys.stderr)
    write_model(out, params, antialiased=antialiased)
    size, before = os.path.getsize(out), os.path.getsize(src)
    print(json.dumps({"output": str(out), "gaussians": int(len(params["means"])), "bytes": size,
                      "bytes_per_gaussian": round(size / len(params["means"]), 2),
                      "size_ratio": round(before / size, 2)}, indent=2))
    return 0


# ------------------------------------------------------------------------------------------------------ view
def _viewer_config(args):
    from .viewer import ViewerConfig

    return ViewerConfig(host=args.host, port=args.port, max_size=args.max_size, moving_size=args.moving_size)


def _dataset_views(saved: dict, cfg, out: Path, split: str = "all"):
    """(ViewEntry list, colour space, background) of the dataset a run was trained on; no views (and a warning) when
    it cannot be loaded any more. A scene file's references are not rendered again: views whose reference is gone
    have no picture in the panel."""
    try:
        ds = _eval_dataset(saved, cfg, out, None, render_missing=False)
    except (InputError, ValueError, OSError, RuntimeError) as e:
        print(f"mi-gs: warning: the run's dataset cannot be loaded ({e}); viewing without its cameras",
              file=sys.stderr)
        return [], "srgb", tuple(cfg.data.background)
    return _entries(ds), ds.color_space, tuple(ds.background)


def _entries(ds):
    from .viewer import ViewEntry

    return [ViewEntry(f"{kind} {v.name}", v.camera, v.load_image if Path(v.image_path).is_file() else None)
            for kind, views in (("train", ds.train), ("test", ds.test)) for v in views]


def _default_camera(g):
    """A camera looking along +z at a model's centre from 2.5 times its radius (90 % of the centres inside)."""
    import numpy as np

    from .data.camera import Camera

    means = np.array(g.means, np.float64).reshape(-1, 3)
    centre = np.median(means, axis=0)
    radius = float(np.percentile(np.linalg.norm(means - centre, axis=1), 90)) or 1.0
    w2c = np.eye(4)
    w2c[:3, 3] = -(centre - [0.0, 0.0, 2.5 * radius])
    return Camera(width=800, height=600, fx=600.0, fy=600.0, cx=400.0, cy=300.0, world_to_camera=w2c, name="default")


def cmd_view(args) -> int:
    from . import run_folder
    from .data.camera import Camera
    from .model.gaussians import Gaussians
    from .viewer import StaticModel, Viewer

    src = Path(args.input)
    if not src.exists():
        raise InputError(f"{src}: not found")
    model = src / run_folder.MODEL if src.is_dir() else src
    if src.is_dir() and not model.is_file():
        raise InputError(f"{model}: missing (is {src} an mi-gs optimize output folder?)")
    if model.suffix.lower() not in MODEL_SUFFIXES:
        raise InputError(f"{src}: expected a model (.ply, .splat or .spz) or an mi-gs optimize output folder")
    raster = _model_raster_config(model, args.antialiased)
    views, color_space, background = [], "srgb", (0.0, 0.0, 0.0)
    if (model.parent / run_folder.CONFIG).is_file():
        try:
            saved = run_folder.read_saved(model.parent, "")
            views, color_space, background = _dataset_views(saved, run_folder.saved_config(saved, model.parent),
                                                            model.parent)
        except ValueError as e:
            print(f"mi-gs: warning: {e}; viewing the model alone", file=sys.stderr)
    if args.background is not None:
        background = _background(args.background)
    g = Gaussians.load(model)
    initial = Camera.from_json(args.camera) if args.camera else None
    if initial is None and not views:
        initial = _default_camera(g)
    viewer = Viewer(StaticModel(g), views, _viewer_config(args), raster=raster, color_space=color_space,
                    background=background, title=f"mi-gs view {src.name}", initial=initial)
    try:
        viewer.start()
    except OSError as e:
        raise InputError(f"--host {args.host} --port {args.port}: cannot serve there ({e.strerror or e})") from None
    print(f"mi-gs view: {g.n:,} Gaussians at {viewer.url} (Ctrl-C stops)", flush=True)
    try:
        viewer.serve_forever()
    except KeyboardInterrupt:                     # (how a viewer is meant to end: not an error)
        pass
    finally:
        viewer.stop()
    return 0


# -------------------------------------------------------------------------------------------------- optimize
def _is_scene_file(path: Path) -> bool:
    return path.suffix.lower() == ".xml"


def _scene_config(args):
    import dataclasses

    from .config import SceneConfig

    kw = {k: getattr(args, k) for k in ("rig", "views", "test_views", "radius", "fov", "spp", "init", "init_points")
          if getattr(args, k) is not None}
    if args.resolution is not None:
        kw["resolution"] = tuple(args.resolution)
    if args.up is not None:
        kw["up"] = tuple(args.up)
    if args.define:
        kw["defines"] = tuple(args.define)
    return dataclasses.replace(SceneConfig(), linear=args.linear, **kw)


def _data_resolution_and_scene(args, scene_file: bool, default_resolution: int):
    """(dataset resolution divisor, SceneConfig) from -r: a film size for a scene .xml, a divisor for a folder."""
    from .config import SceneConfig

    if scene_file:
        if args.resolution is not None and (len(args.resolution) > 2 or min(args.resolution) < 16):
            raise InputError("for a scene .xml, --resolution is the film size in pixels, W [H] (at least 16), "
                             f"not a divisor: got {' '.join(map(str, args.resolution))}")
        return 1, _scene_config(args)
    if args.resolution is not None and len(args.resolution) != 1:
        raise InputError("-r/--resolution takes one divisor for a dataset folder (e.g. -r 4)")
    return (args.resolution[0] if args.resolution else default_resolution), SceneConfig()


def _train_config(args, scene_file: bool = False):
    import dataclasses

    from .config import DataConfig, DensifyConfig, MCMCConfig, OptimConfig, RasterConfig, TrainConfig

    d, o, dn = DataConfig(), OptimConfig(), DensifyConfig()
    resolution, scene = _data_resolution_and_scene(args, scene_file, d.resolution)
    data = dataclasses.replace(d, resolution=resolution, background=_background(args.background)
                               if args.background is not None else (1.0, 1.0, 1.0) if args.white_background
                               else d.background, test_every=args.test_every, seed=args.seed,
                               random_points=args.random_points if args.random_points is not None
                               else d.random_points)
    opt_kw = {"random_background": args.random_background}
    if args.iterations is not None:
        opt_kw["iterations"] = args.iterations
        opt_kw["position_lr_max_steps"] = args.iterations
    if args.sh_degree is not None:
        opt_kw["sh_degree"] = args.sh_degree
    if args.depth_weight is not None:
        if not scene_file:
            raise InputError("--depth-weight needs the exact depth of a Mitsuba scene: give a scene .xml")
        opt_kw["depth_weight"], opt_kw["depth_weight_final"] = args.depth_weight, args.depth_weight / 100.0
    optim = dataclasses.replace(o, **opt_kw)
    dens_kw = {}
    if args.iterations is not None and args.iterations < o.iterations:
        # a shorter schedule keeps the paper's proportions (densify until half the run)
        dens_kw["densify_until_iter"] = min(dn.densify_until_iter, args.iterations // 2)
    densify = dataclasses.replace(dn, absgrad=args.absgrad, **dens_kw)
    strategy = args.strategy or TrainConfig().strategy
    mc = MCMCConfig()
    mcmc_kw = {} if args.max_gaussians is None else {"cap_max": args.max_gaussians}
    if args.iterations is not None and args.iterations < o.iterations:
        # the paper's proportion: refine until 25k of 30k iterations
        mcmc_kw["refine_stop_iter"] = min(mc.refine_stop_iter, args.iterations * 5 // 6)
    save = tuple(i for i in TrainConfig().save_iterations if i < optim.iterations)
    raster = dataclasses.replace(RasterConfig(), antialiased=args.antialiased)
    return TrainConfig(data=data, optim=optim, densify=densify, scene=scene, raster=raster, seed=args.seed,
                       strategy=strategy, mcmc=dataclasses.replace(mc, **mcmc_kw),
                       checkpoint_every=args.checkpoint_every, eval_every=args.eval_every, save_iterations=save)


# What each optimize option sets in the TrainConfig: on --resume, an option given again must agree with the run
# (checkpoint_every, eval_every and cache only change how the run is carried out, and iterations may extend it)
_RUN_FIELDS = {
    "resolution": ("data.resolution", "scene.resolution"), "background": ("data.background",),
    "white_background": ("data.background",), "random_background": ("optim.random_background",),
    "sh_degree": ("optim.sh_degree",), "test_every": ("data.test_every",), "seed": ("seed", "data.seed"),
    "random_points": ("data.random_points",), "rig": ("scene.rig",), "views": ("scene.views",),
    "test_views": ("scene.test_views",), "radius": ("scene.radius",), "fov": ("scene.fov",), "up": ("scene.up",),
    "spp": ("scene.spp",), "linear": ("scene.linear",), "init": ("scene.init",),
    "init_points": ("scene.init_points",), "define": ("scene.defines",), "antialiased": ("raster.antialiased",),
    "absgrad": ("densify.absgrad",), "strategy": ("strategy",), "max_gaussians": ("mcmc.cap_max",),
    "depth_weight": ("optim.depth_weight",),
}


def _field(cfg, dotted: str):
    for name in dotted.split("."):
        cfg = getattr(cfg, name)
    return cfg


def _resumed_config(args, src: Path, out: Path, saved: dict):
    """The saved run's TrainConfig, checked against the options given again on the command line; ``--iterations``
    may move the end of the run (the schedules stay the run's), ``--checkpoint-every`` / ``--eval-every`` apply."""
    import dataclasses

    from . import run_folder

    cfg = run_folder.saved_config(saved, out)
    given = _train_config(args, scene_file=_is_scene_file(src))
    differ = []
    from .data.scene_file import parse_defines

    def same(name: str) -> bool:
        a, b = _field(cfg, name), _field(given, name)
        return parse_defines(a) == parse_defines(b) if name == "scene.defines" else a == b   # -D order is free

    for option in sorted(args.explicit & set(_RUN_FIELDS)):
        for name in _RUN_FIELDS[option]:
            if not same(name):
                differ.append(f"--{option.replace('_', '-')} gives {name} = {_field(given, name)!r}, the run has "
                              f"{_field(cfg, name)!r}")
    if differ:
        raise InputError(f"--resume: {out / run_folder.CONFIG}: the options differ from the run's settings: "
                         f"{'; '.join(differ)} (resume without them, or start a new run)")
    if "iterations" in args.explicit:
        cfg = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, iterations=args.iterations))
    for option in ("checkpoint_every", "eval_every"):
        if option in args.explicit:
            cfg = dataclasses.replace(cfg, **{option: getattr(args, option)})
    return cfg


def _check_resumed_dataset(src: Path, out: Path, saved: dict, fingerprint: str | None) -> None:
    """A resumed run trains on the folder it started on, with the same content."""
    from . import run_folder

    if Path(saved["dataset"]) != src.resolve():
        raise InputError(f"--resume: the run in {out} was trained on {saved['dataset']}, not on {src.resolve()} "
                         f"(recorded in {out / run_folder.CONFIG})")
    recorded = saved.get("dataset_fingerprint")
    if fingerprint is not None and recorded is not None and recorded.split(":")[0] != fingerprint.split(":")[0]:
        print(f"mi-gs: warning: {out / run_folder.CONFIG} holds a dataset fingerprint of an earlier mi-gs; the "
              "dataset's content is not compared this time (the run's record gets the current one)", file=sys.stderr)
    elif fingerprint is not None and recorded is not None and recorded != fingerprint:
        raise InputError(f"--resume: {src}: the dataset changed since the run in {out} started (its images, "
                         "cameras or points differ); start a new run (--overwrite or another folder)")


def _optimize_config(args, src: Path, out: Path):
    """(TrainConfig, the saved record of the run being resumed or None); nothing is written."""
    from . import run_folder

    if args.resume and args.overwrite:
        raise InputError("give at most one of --resume and --overwrite")
    if args.resume and args.settings:
        raise InputError("--set cannot change a run being resumed (its settings are in OUTDIR/config.json)")
    if args.resume:
        saved = run_folder.read_saved(out, "nothing to resume (no config.json in the output folder)")
        return _resumed_config(args, src, out, saved), saved
    run_folder.check_new_run(out, args.overwrite)
    cfg = _train_config(args, scene_file=_is_scene_file(src))
    try:
        cfg = cfg.with_settings(args.settings or ())
        _check_strategy_options(cfg, args)
        _check_settings(cfg, _is_scene_file(src))
        from .optim.trainer import make_strategy

        make_strategy(cfg, 1.0, white_background=False)        # (refuses an unknown strategy or bad settings)
        return cfg, None
    except ValueError as e:
        raise InputError(str(e)) from None


# the settings section each strategy reads (an option of the other strategy would be silently ignored)
_STRATEGY_SECTIONS = {"default": "densify", "mcmc": "mcmc"}


def _check_strategy_options(cfg, args) -> None:
    """Refuses an option or ``--set`` of the strategy the run does not use."""
    if args.max_gaussians is not None and cfg.strategy != "mcmc":
        raise InputError("--max-gaussians is the budget of --strategy mcmc (the default strategy has none)")
    if cfg.densify.absgrad and cfg.strategy != "default":
        raise InputError(f"--absgrad is an option of the default strategy; --strategy {cfg.strategy} does not "
                         f"densify on gradients (leave out one of them)")
    own = _STRATEGY_SECTIONS.get(cfg.strategy)
    if own is None:          # (an unknown strategy: make_strategy names it)
        return
    for text in args.settings or ():
        section = str(text).partition("=")[0].strip().partition(".")[0]
        if section in _STRATEGY_SECTIONS.values() and section != own:
            other = next(k for k, v in _STRATEGY_SECTIONS.items() if v == section)
            raise InputError(f"setting {str(text).partition('=')[0].strip()!r}: the {section} section configures "
                             f"--strategy {other}, not the {cfg.strategy} strategy of this run")


def _check_settings(cfg, scene_file: bool) -> None:
    """Settings that ``--set`` can give and that would otherwise fail only once the run has started."""
    from .data.pointcloud import RANDOM_INITS

    if cfg.data.random_init not in RANDOM_INITS:
        raise InputError(f"setting 'data.random_init': {cfg.data.random_init!r} is not one of "
                         f"{', '.join(RANDOM_INITS)}")
    if cfg.optim.depth_weight > 0 and not scene_file:
        raise InputError("optim.depth_weight needs the exact depth of a Mitsuba scene: give a scene .xml")
    if cfg.optim.depth_weight > 0 and not cfg.optim.depth_weight_final > 0:
        raise InputError("optim.depth_weight_final must be > 0 with optim.depth_weight (the weight decays "
                         "exponentially to it; --depth-weight W sets W and W/100)")


def cmd_optimize(args) -> int:
    from . import run_folder
    from .io_utils import check_output_folder

    out = Path(args.output)
    src = Path(args.scene)
    if not src.exists():
        raise InputError(f"{src}: not found")
    check_output_folder(out)
    cfg, saved = _optimize_config(args, src, out)
    created = not out.exists()
    lock = run_folder.RunLock(out)
    lock.acquire()                                # before anything is written into the folder
    try:
        run_folder.remove_temporary_files(out)
        return _optimize_locked(args, src, out, cfg, saved)
    except BaseException:
        if created:                               # (a run refused before it wrote anything leaves no folder)
            lock.release_and_remove_if_empty()
        raise
    finally:
        lock.release()


def _optimize_locked(args, src: Path, out: Path, cfg, saved) -> int:
    from . import run_folder
    from .data.dataset import check_trainable_size, fingerprint, verify_images
    from .optim.trainer import Trainer, TrainingDiverged

    cache = args.cache or run_folder.saved_cache(saved, out)
    # everything is checked (references rendered, every image decoded) before an earlier run is removed
    ds = _load_input(src, cfg, out, cache=cache, progress=not args.quiet, expect_key=run_folder.saved_key(saved))
    check_trainable_size(ds)
    record = {}
    if ds.layout != "mitsuba":                    # (a scene file's references carry their own key)
        record["dataset_fingerprint"] = fingerprint(ds)
    if saved is not None:
        _check_resumed_dataset(src, out, saved, record.get("dataset_fingerprint"))
    verify_images(ds.test, progress=not args.quiet)
    trainer = Trainer(ds, cfg, out, progress=not args.quiet)     # (decodes the training images)
    viewer = _training_viewer(args, trainer, ds, cfg) if args.view else None
    try:
        if args.overwrite:
            run_folder.clear_run(out)
        metrics = trainer.run(resume=args.resume, record=record,
                              monitor=None if viewer is None else viewer.training_monitor)
        if ds.layout == "mitsuba":
            from .plugins.scene_xml import write_gaussian_scene

            cam = (ds.test or ds.train)[0].camera
            write_gaussian_scene(out / run_folder.GAUSSIAN_SCENE, run_folder.MODEL, cam, ds.color_space,
                                 ds.background, antialiased=cfg.raster.antialiased)
    except TrainingDiverged as e:
        if viewer is not None:
            viewer.close()
        print(f"mi-gs: error: {e}", file=sys.stderr)
        return 3
    except BaseException:
        if viewer is not None:
            viewer.close()
        raise
    print(json.dumps({"output": str(out), **metrics["mean"], "gaussians": metrics["gaussians"],
                      "training_seconds": metrics["training_seconds"]}, indent=2), flush=True)
    if viewer is not None and viewer.viewer is None:
        return 0
    if viewer is not None:
        print(f"mi-gs: training done; the viewer stays at {viewer.viewer.url} (Ctrl-C stops)", file=sys.stderr,
              flush=True)
        try:
            viewer.viewer.serve_forever()
        except KeyboardInterrupt:                 # (the run is done: stopping the viewer is not an error)
            pass
        finally:
            viewer.close()
    return 0


def _training_viewer(args, trainer, ds, cfg):
    from .viewer import TrainingView, Viewer

    live = TrainingView(trainer)
    viewer = Viewer(live, _entries(ds), _viewer_config(args), raster=cfg.raster, color_space=ds.color_space,
                    background=tuple(ds.background), title=f"mi-gs optimize {Path(args.output).name}")
    live.viewer = viewer
    try:
        viewer.start()
    except OSError as e:
        raise InputError(f"--host {args.host} --port {args.port}: cannot serve there ({e.strerror or e})") from None
    print(f"mi-gs: training view at {viewer.url}", file=sys.stderr, flush=True)
    return live


def _load_input(src: Path, cfg, out: Path, cache: str | None = None, progress: bool = True,
                expect_key: str | None = None, render_missing: bool = True):
    """The dataset of a scene folder, or of a Mitsuba scene file (references cached in ``cache`` or
    OUTDIR/references; those missing rendered unless ``render_missing`` is False)."""
    d = cfg.data
    if _is_scene_file(src):
        from .data.scene_dataset import load_scene_dataset
        from .run_folder import references_root

        return load_scene_dataset(src, cfg.scene, cache_root=references_root(out, cache), background=d.background,
                                  test_every=d.test_every, seed=d.seed, progress=progress,
                                  log=lambda line: print(line, file=sys.stderr, flush=True), expect_key=expect_key,
                                  render_missing=render_missing)
    from .data.dataset import load_dataset

    return load_dataset(src, resolution=d.resolution, background=d.background, test_every=d.test_every,
                        random_points=d.random_points, seed=d.seed, masks=d.masks,
                        random_init=d.random_init)


# ------------------------------------------------------------------------------------------------------ eval
def _eval_dataset(saved: dict, cfg, out: Path, dataset: str | None, render_missing: bool = True):
    """The dataset a run is evaluated on: ``dataset``, else the one it was trained on (a scene file's references
    from the run's cache, rendered again only if they are gone and ``render_missing``; no initial points)."""
    import dataclasses

    from . import run_folder
    from .data.dataset import load_dataset

    src = Path(dataset or saved["dataset"])
    if _is_scene_file(src):
        cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, init="random", init_points=1))
        return _load_input(src, cfg, out, cache=run_folder.saved_cache(saved, out),
                           expect_key=run_folder.saved_key(saved), render_missing=render_missing)
    d = cfg.data
    return load_dataset(src, resolution=d.resolution, background=d.background, test_every=d.test_every,
                        random_points=0, masks=d.masks)


def cmd_eval(args) -> int:
    from . import run_folder

    out = Path(args.run)
    ply = out / run_folder.MODEL
    for p in (out / run_folder.CONFIG, ply):
        if not p.exists():
            raise InputError(f"{p}: missing (is {out} an mi-gs optimize output folder?)")
    saved = run_folder.read_saved(out, "missing")
    cfg = run_folder.saved_config(saved, out)
    with run_folder.RunLock(out):                 # (not while a run is writing the folder)
        return _eval_locked(args, out, ply, saved, cfg)


def _eval_locked(args, out: Path, ply: Path, saved: dict, cfg) -> int:
    from . import run_folder
    from .evaluate import evaluate_views, scores_report
    from .model.gaussians import Gaussians
    from .report import write_json

    ds = _eval_dataset(saved, cfg, out, args.dataset)
    views = ds.test if ds.test else ds.train
    g = Gaussians.load_ply(ply)
    scores, note = evaluate_views(g, views, tuple(ds.background), cfg=cfg.raster, color_space=ds.color_space)
    report = scores_report(scores, note)
    note = report.pop("lpips_note", None)
    result = {"split": "test" if ds.test else "train", **report, "gaussians": g.n,
              **({"lpips_note": note} if note else {})}
    write_json(out / run_folder.EVAL, result)
    print(json.dumps({"output": str(out / run_folder.EVAL), **result["mean"], "gaussians": g.n,
                      **({"lpips_note": note} if note else {})}, indent=2))
    return 0


# --------------------------------------------------------------------------------------------------- convert
def cmd_convert(args) -> int:
    from .data.convert import convert

    res = convert(args.images, args.output, camera_model=args.camera_model, resize=args.resize,
                  overwrite=args.overwrite, num_threads=args.threads, max_image_size=args.max_image_size,
                  progress=lambda line: print(line, flush=True))
    print(json.dumps({"scene": str(res.out_dir), "images": res.num_images, "registered": res.num_registered,
                      "points": res.num_points, "mean_reprojection_error_px": round(res.mean_reprojection_error, 4)},
                     indent=2))
    return 0


# ------------------------------------------------------------------------------------------------------ main
def _add_define(parser, help_text: str) -> None:
    parser.add_argument("-D", "--define", action="append", default=None, metavar="KEY=VALUE", help=help_text)


def _add_info(sub) -> None:
    from .config import DataConfig

    s = sub.add_parser("info", help="summarize a 3DGS .ply, a dataset folder or a Mitsuba scene .xml")
    s.add_argument("path")
    s.add_argument("-r", "--resolution", type=positive_int, default=DataConfig().resolution,
                   help="dataset resolution divisor")
    _add_define(s, "set a scene parameter (scene .xml only), as mitsuba -D; repeatable")
    s.set_defaults(func=cmd_info)


def _add_render(sub) -> None:
    from .config import DataConfig

    s = sub.add_parser("render", help="render a model (.ply, .splat, .spz; from a camera JSON or a dataset's views) "
                                      "or a scene .xml")
    s.add_argument("input", help="model.ply|.splat|.spz or scene.xml")
    s.add_argument("--camera", help="camera JSON (see README)")
    s.add_argument("--dataset", help="dataset folder whose views to render")
    s.add_argument("--split", choices=("train", "test", "all"), default="test")
    s.add_argument("-o", "--output", required=True, help="output .exr/.png file, or folder with --dataset")
    s.add_argument("-r", "--resolution", type=positive_int, default=None,
                   help=f"with --dataset: divide its image size by this (default {DataConfig().resolution})")
    s.add_argument("--background", type=finite_float, nargs="+", default=None,
                   help="background colour (1 or 3 values)")
    s.add_argument("--sh-degree", type=sh_degree, default=None, help="active SH degree (default: the model's)")
    s.add_argument("--color-space", choices=("srgb", "linear"), default="srgb",
                   help="what the model's colours are (3DGS models trained on photos: srgb)")
    s.add_argument("--alpha", action="store_true", help="write an alpha channel")
    s.add_argument("--antialiased", action=argparse.BooleanOptionalAction, default=None,
                   help="render with Mip-Splatting's 2D filter (default: as the run whose config.json sits beside "
                        "the model was trained, or as an .spz file records, else off)")
    s.add_argument("--spp", type=positive_int, default=None, help="samples per pixel (scene .xml only)")
    s.add_argument("--sensor", type=non_negative_int, default=0, help="sensor index (scene .xml only)")
    _add_define(s, "set a scene parameter (scene .xml only), as mitsuba -D; repeatable")
    s.set_defaults(func=cmd_render)


def _add_scene_options(s) -> None:
    from .config import SceneConfig
    from .data.scene_init import INIT_METHODS
    from .data.scene_rig import FALLBACK_FOV, FALLBACK_SPP, FALLBACK_UP, RIGS

    sc = SceneConfig()
    g = s.add_argument_group("Mitsuba scene (.xml) input")
    g.add_argument("--rig", choices=RIGS, default=None,
                   help=f"cameras: the scene's sensors, or generated around its bounding box (default {sc.rig}: the "
                        "sensors if the scene declares several, else hemisphere)")
    g.add_argument("--views", type=positive_int, default=None,
                   help=f"generated training cameras (default {sc.views}; --seed also picks the rig, so another seed "
                        "renders new references)")
    g.add_argument("--test-views", type=non_negative_int, default=None,
                   help=f"generated held-out cameras (default {sc.test_views})")
    g.add_argument("--radius", type=positive_float, default=None,
                   help="rig radius (default: the bounding sphere fills the view)")
    g.add_argument("--fov", type=field_of_view, default=None, help="horizontal field of view in degrees (default: the "
                                                           f"sensor's, else {FALLBACK_FOV:g})")
    g.add_argument("--up", type=finite_float, nargs=3, default=None,
                   help=f"world up (default: the sensor's, else {' '.join(f'{u:g}' for u in FALLBACK_UP)})")
    g.add_argument("--spp", type=positive_int, default=None, help="reference samples per pixel (default: the sensor's, "
                                                         f"else {FALLBACK_SPP})")
    g.add_argument("--linear", action="store_true",
                   help="train on linear radiance (default: on the sRGB-encoded references)")
    g.add_argument("--init", choices=INIT_METHODS, default=None,
                   help=f"initial points (default {sc.init}): sampled on the shapes and coloured by the references, "
                        "random in the bounding box, or structure from motion")
    g.add_argument("--init-points", type=positive_int, default=None,
                   help=f"initial points for shapes/random (default {sc.init_points})")
    g.add_argument("--cache", default=None, help="folder for the cached references (default OUTDIR/references)")
    _add_define(g, "set a scene parameter (<default name=\"KEY\">), as mitsuba -D; repeatable")


def _add_optimize(sub) -> None:
    from .config import DataConfig, MCMCConfig, OptimConfig, TrainConfig
    from .data.scene_rig import FALLBACK_RESOLUTION

    d, o, t = DataConfig(), OptimConfig(), TrainConfig()
    s = sub.add_parser("optimize", help="fit Gaussians to a COLMAP / Blender / instant-ngp scene folder, or to "
                                        "path-traced references of a Mitsuba scene .xml")
    s.add_argument("scene", help="scene folder, or Mitsuba scene file (.xml)")
    s.add_argument("-o", "--output", required=True, help="output folder")
    s.add_argument("--iterations", type=positive_int, default=None, help=f"default {o.iterations} (the paper's)")
    s.add_argument("-r", "--resolution", type=positive_int, nargs="+", default=None,
                   help=f"scene folder: divide the image size by this (default {d.resolution}); scene .xml: the film "
                        f"size of generated cameras, W [H] (default: the scene's sensor's, else "
                        f"{FALLBACK_RESOLUTION[0]})")
    s.add_argument("--white-background", action="store_true", help="composite RGBA images over white")
    s.add_argument("--background", type=finite_float, nargs="+", default=None,
                   help="background colour (1 or 3 values)")
    s.add_argument("--random-background", action="store_true", help="random background colour per iteration")
    s.add_argument("--absgrad", action="store_true",
                   help="densify on AbsGS's absolute per-pixel gradients (gsplat's absgrad), with its own threshold "
                        "(densify.absgrad_threshold, default 0.0008)")
    s.add_argument("--depth-weight", type=positive_float, default=None,
                   help="scene .xml: add an inverse-depth L1 against the exact depth Mitsuba gives, weighted W at the "
                        "start and decaying to W/100 (the 2024 reference's schedule with W = 1)")
    s.add_argument("--strategy", choices=("default", "mcmc"), default=None,
                   help="densification: 'default' (the paper's clone / split / prune) or 'mcmc' (3DGS as Markov "
                        "Chain Monte Carlo, gsplat's MCMCStrategy: relocation, growth up to --max-gaussians)")
    s.add_argument("--max-gaussians", type=positive_int, default=None,
                   help=f"--strategy mcmc: the most Gaussians the run may have (default {MCMCConfig().cap_max:,})")
    s.add_argument("--antialiased", action="store_true",
                   help="Mip-Splatting's 2D filter (gsplat's antialiased mode); the model must then be rendered "
                        "with it, which config.json and gaussians.xml record")
    s.add_argument("--sh-degree", type=sh_degree, default=None, help=f"maximum SH degree (default {o.sh_degree})")
    s.add_argument("--test-every", type=non_negative_int, default=d.test_every,
                   help="hold out every N-th image (COLMAP/ngp; 0: none)")
    s.add_argument("--random-points", type=positive_int, default=None,
                   help=f"initial random points for layouts without SfM points (default {d.random_points})")
    s.add_argument("--seed", type=non_negative_int, default=t.seed)
    s.add_argument("--set", action="append", default=None, metavar="SECTION.FIELD=VALUE", dest="settings",
                   help="set any field of the training configuration (mi_gaussians/config.py), applied after the "
                        "other options, e.g. --set densify.min_opacity=0.1 --set optim.feature_lr=0.005; repeatable")
    s.add_argument("--checkpoint-every", type=positive_int, default=t.checkpoint_every)
    s.add_argument("--eval-every", type=non_negative_int, default=t.eval_every, help="test PSNR for the curves every N iterations")
    s.add_argument("--resume", action="store_true", help="continue the run saved in the output folder")
    s.add_argument("--overwrite", action="store_true",
                   help="start a new run in an output folder that holds one (cached references are kept)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--view", action="store_true",
                   help="serve the viewer while training (mi-gs view's options below), with the loss curve")
    _add_viewer_options(s)
    _add_scene_options(s)
    s.set_defaults(func=cmd_optimize)


def _add_eval(sub) -> None:
    s = sub.add_parser("eval", help="recompute the metrics of a saved run on its test views")
    s.add_argument("run", help="an mi-gs optimize output folder")
    s.add_argument("--dataset", default=None, help="dataset folder (default: the one the run was trained on)")
    s.set_defaults(func=cmd_eval)


def _add_export(sub) -> None:
    s = sub.add_parser("export", help="write a model as .splat (32 bytes per Gaussian, web viewers), .spz (Niantic's "
                                      "compressed format) or .ply")
    s.add_argument("input", help="model.ply, .splat or .spz")
    s.add_argument("-o", "--output", required=True, help="out.splat, out.spz or out.ply")
    s.add_argument("--sh-degree", type=sh_degree, default=None,
                   help="keep the SH bands up to this degree (default: all the model has; .splat keeps degree 0)")
    s.add_argument("--antialiased", action=argparse.BooleanOptionalAction, default=None,
                   help="record in an .spz that the model renders anti-aliased (default: as the run whose "
                        "config.json sits beside the model was trained)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    s.set_defaults(func=cmd_export)


def _add_viewer_options(s) -> None:
    from .viewer import ViewerConfig

    v = ViewerConfig()
    s.add_argument("--port", type=positive_int, default=v.port, help=f"viewer port (default {v.port})")
    s.add_argument("--host", default=v.host, help=f"viewer address (default {v.host}; 0.0.0.0: every interface)")
    s.add_argument("--max-size", type=positive_int, default=v.max_size,
                   help=f"longest image side at rest (default {v.max_size})")
    s.add_argument("--moving-size", type=positive_int, default=v.moving_size,
                   help=f"longest image side while the camera moves (default {v.moving_size})")


def _add_view(sub) -> None:
    s = sub.add_parser("view", help="look at a model in the browser (viser): orbit, render modes, dataset cameras")
    s.add_argument("input", help="model.ply|.splat|.spz, or an mi-gs optimize output folder")
    s.add_argument("--camera", help="camera JSON to start from (default: the dataset's first camera)")
    s.add_argument("--background", type=finite_float, nargs="+", default=None,
                   help="background colour (1 or 3 values; default: the run's)")
    s.add_argument("--antialiased", action=argparse.BooleanOptionalAction, default=None,
                   help="render with Mip-Splatting's 2D filter (default: as the run was trained)")
    _add_viewer_options(s)
    s.set_defaults(func=cmd_view)


def _add_convert(sub) -> None:
    from .config import ConvertConfig

    c = ConvertConfig()
    s = sub.add_parser("convert", help="structure-from-motion with pycolmap: images folder -> COLMAP scene")
    s.add_argument("images", help="folder of input images")
    s.add_argument("-o", "--output", required=True, help="scene folder to create (images/ + sparse/0)")
    s.add_argument("--camera-model", default=c.camera_model)
    s.add_argument("--resize", action="store_true", default=c.resize, help="also write images_2/4/8")
    s.add_argument("--overwrite", action="store_true")
    s.add_argument("--threads", type=int, default=c.num_threads)
    s.add_argument("--max-image-size", type=positive_int, default=c.max_image_size)
    s.set_defaults(func=cmd_convert)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``mi-gs: error: argument --iterations: ... (see mi-gs optimize -h)`` instead
    of the usage block and the error."""

    def error(self, message: str):
        self.exit(EXIT_INPUT_ERROR, f"mi-gs: error: {message} (see {self.prog} -h)\n")


_VARIANT_HELP = "Mitsuba variant: llvm_ad_rgb or cuda_ad_rgb (default: cuda_ad_rgb if a GPU is available)"


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="mi-gs", description="3D Gaussian Splatting as a Mitsuba 3 plugin.")
    p.add_argument("--variant", default=None, help=_VARIANT_HELP)
    sub = p.add_subparsers(dest="command", required=True)
    for add in (_add_info, _add_render, _add_optimize, _add_eval, _add_export, _add_view, _add_convert):
        add(sub)
    for s in sub.choices.values():
        # (also after the subcommand; SUPPRESS: given there, it replaces the one before the subcommand)
        s.add_argument("--variant", default=argparse.SUPPRESS, help=_VARIANT_HELP)
    return p


def _explicit_options(argv) -> set[str]:
    """The destinations of the options given on the command line (not left at their defaults)."""
    parser = build_parser()
    parsers = [parser] + [a for act in parser._actions if isinstance(act, argparse._SubParsersAction)
                          for a in act.choices.values()]
    for p in parsers:
        for action in p._actions:
            if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                action.default = argparse.SUPPRESS
    return set(vars(parser.parse_args(argv)))


def main(argv=None) -> int:
    """The error boundary: every expected failure is one line ``mi-gs: error: ...`` on stderr and exit status 2
    (argparse's own errors included); a diverged run exits 3, Ctrl-C 130."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.explicit = _explicit_options(argv)
    try:
        _set_variant(args.variant)
        import mi_gaussians  # noqa: F401  (registers the plugins for the variant)

        status = args.func(args)
        sys.stdout.flush()
        return status
    except BrokenPipeError:
        return _broken_pipe()
    except (InputError, ValueError, OSError) as e:
        if isinstance(e, OSError) and e.errno == errno.EPIPE:
            return _broken_pipe()
        return _error(_one_line(e) if not isinstance(e, OSError) else _os_error(e))
    except RuntimeError as e:   # Mitsuba reports scene-file problems as RuntimeError
        return _error(_one_line(e))
    except KeyboardInterrupt:
        print("mi-gs: interrupted", file=sys.stderr)
        return 130


def _error(message: str) -> int:
    print(f"mi-gs: error: {message}", file=sys.stderr)
    return EXIT_INPUT_ERROR


def _broken_pipe() -> int:
    # the reader of our output went away (``mi-gs info ... | head``): say so once, and keep Python from
    # complaining again when it flushes stdout at exit
    import os

    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except OSError:
        pass
    return _error("standard output was closed before everything was written (broken pipe)")


def _os_error(e: OSError) -> str:
    """``[Errno 21] Is a directory: 'x.png'`` -> ``x.png: is a directory``."""
    what = (e.strerror or str(e)).rstrip(".")
    what = what[0].lower() + what[1:] if what else "cannot be written"
    names = [str(n) for n in (e.filename, e.filename2) if n is not None]
    return f"{' -> '.join(names)}: {what}" if names else _one_line(e)


def _one_line(e: BaseException) -> str:
    # Dr.Jit/Mitsuba wrap errors raised inside custom operations ("... (see above)"): report the innermost cause
    while (e.__cause__ or e.__context__) is not None and "see above" in str(e):
        e = e.__cause__ or e.__context__
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return " ".join(lines) if len(lines) <= 3 else " ".join(lines[:3]) + " ..."


if __name__ == "__main__":
    sys.exit(main())
