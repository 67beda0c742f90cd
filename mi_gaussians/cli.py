"""``mi-gs``: the command-line interface. Arguments -> config dataclasses -> library calls.

Every subcommand selects the Mitsuba variant first (``--variant``; default ``cuda_ad_rgb`` when a CUDA device is
present, else ``llvm_ad_rgb``). Errors in the user's input print one line, ``mi-gs: error: <file>: <problem>``, and
exit with status 2; nothing is half-written (all outputs are written atomically).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

EXIT_INPUT_ERROR = 2


class InputError(Exception):
    """A problem with the user's input, reported as one line."""


def _default_variant() -> str:
    import drjit as dr

    return "cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb"


def _set_variant(name: str | None) -> None:
    import mitsuba as mi

    variant = name or _default_variant()
    if variant not in mi.variants():
        raise InputError(f"unknown Mitsuba variant {variant!r} (available: {', '.join(mi.variants())})")
    mi.set_variant(variant)


def _background(values) -> tuple[float, float, float]:
    if values is None:
        return (0.0, 0.0, 0.0)
    if len(values) == 1:
        return (values[0],) * 3
    if len(values) != 3:
        raise InputError("--background takes one value or three (r g b)")
    return tuple(values)


# ------------------------------------------------------------------------------------------------------ info
def cmd_info(args) -> int:
    path = Path(args.path)
    if not path.exists():
        raise InputError(f"{path}: not found")
    if path.suffix.lower() == ".ply":
        import numpy as np

        from .model.ply import read_ply

        p = read_ply(path)
        n = p["means"].shape[0]
        deg = {0: 0, 3: 1, 8: 2, 15: 3}[p["sh_rest"].shape[1]]
        info = {"file": str(path), "gaussians": n, "sh_degree": deg}
        if n:
            opac = 1.0 / (1.0 + np.exp(-p["opacities"].astype(np.float64)))
            sig = np.exp(p["scales"].astype(np.float64)).max(axis=1)
            info.update(bbox_min=p["means"].min(0).round(4).tolist(), bbox_max=p["means"].max(0).round(4).tolist(),
                        opacity_mean=round(float(opac.mean()), 4),
                        sigma_max_median=float(np.median(sig)))
    elif path.suffix.lower() == ".xml":
        import mitsuba as mi

        scene = mi.load_file(str(path))
        info = {"file": str(path), "integrator": scene.integrator().class_name() if scene.integrator() else None,
                "sensors": [s.id() or s.class_name() for s in scene.sensors()],
                "shapes": len(scene.shapes()), "bbox": [list(scene.bbox().min), list(scene.bbox().max)]}
    else:
        from .data.dataset import load_dataset

        ds = load_dataset(path, resolution=args.resolution)
        cam = ds.train[0].camera
        info = {"dataset": str(path), "layout": ds.layout, "train_views": len(ds.train), "test_views": len(ds.test),
                "image_size": [cam.width, cam.height], "fx": round(cam.fx, 4), "fy": round(cam.fy, 4),
                "cx": round(cam.cx, 4), "cy": round(cam.cy, 4), "color_space": ds.color_space,
                "points": 0 if ds.points_xyz is None else int(ds.points_xyz.shape[0]),
                "extent": round(ds.extent, 6)}
    print(json.dumps(info, indent=2))
    return 0


# ---------------------------------------------------------------------------------------------------- render
def _render_gaussians_views(args, views, color_space: str, out_paths) -> None:
    import numpy as np
    from tqdm import tqdm

    from .imwrite import write_image
    from .model.gaussians import Gaussians
    from .raster.rasterize import render

    g = Gaussians.load_ply(args.input)
    bg = _background(args.background)
    for (name, cam), outs in tqdm(list(zip(views, out_paths)), desc="render", unit="view", disable=len(views) < 2):
        out = render(g, cam, background=bg, sh_degree=args.sh_degree)
        rgb = np.array(out.rgb, dtype=np.float32)
        if args.alpha:
            rgb = np.concatenate([rgb, np.array(out.alpha, dtype=np.float32)[..., None]], axis=-1)
        for p in outs:
            write_image(p, rgb, color_space)


def _outputs_for(path: Path) -> list[Path]:
    ext = path.suffix.lower()
    if ext not in (".exr", ".png"):
        raise InputError(f"{path}: unsupported output format {ext or '(none)'} (use .exr or .png)")
    return [path]


def cmd_render(args) -> int:
    src = Path(args.input)
    if not src.exists():
        raise InputError(f"{src}: not found")
    out = Path(args.output)
    if src.suffix.lower() == ".xml":
        import mitsuba as mi
        import numpy as np

        from .imwrite import write_image

        from .data.mitsuba_scene import load_file

        scene = load_file(src, args.define)
        if not scene.sensors():
            raise InputError(f"{src}: the scene has no sensor")
        if args.sensor >= len(scene.sensors()):
            raise InputError(f"{src}: sensor index {args.sensor} out of range ({len(scene.sensors())} sensors)")
        img = np.array(mi.render(scene, sensor=args.sensor, spp=args.spp or 0), dtype=np.float32)
        for p in _outputs_for(out):
            write_image(p, img[..., :4] if img.shape[-1] >= 4 else img[..., :3], "linear")
            print(p)
        return 0
    if src.suffix.lower() != ".ply":
        raise InputError(f"{src}: expected a 3DGS .ply model or a Mitsuba scene .xml")
    if (args.camera is None) == (args.dataset is None):
        raise InputError("give exactly one of --camera CAM.json or --dataset DIR")
    if args.camera is not None:
        from .data.camera import Camera

        cam = Camera.from_json(args.camera)
        _render_gaussians_views(args, [(cam.name or "view", cam)], args.color_space, [_outputs_for(out)])
        print(out)
        return 0
    from .data.dataset import load_dataset

    ds = load_dataset(args.dataset, resolution=args.resolution, background=_background(args.background))
    views = {"train": ds.train, "test": ds.test, "all": ds.views}[args.split]
    if not views:
        raise InputError(f"{args.dataset}: the {args.split} split is empty")
    if out.suffix:
        raise InputError(f"{out}: with --dataset, -o names an output folder")
    out.mkdir(parents=True, exist_ok=True)
    paths = [[out / f"{Path(v.name).stem}.exr", out / f"{Path(v.name).stem}.png"] for v in views]
    _render_gaussians_views(args, [(v.name, v.camera) for v in views], ds.color_space, paths)
    print(f"{len(views)} views -> {out}")
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


def _train_config(args, scene_file: bool = False):
    import dataclasses

    from .config import DataConfig, DensifyConfig, OptimConfig, SceneConfig, TrainConfig

    d, o, dn = DataConfig(), OptimConfig(), DensifyConfig()
    if scene_file:
        if args.resolution is not None and (len(args.resolution) > 2 or min(args.resolution) < 16):
            raise InputError("for a scene .xml, --resolution is the film size in pixels, W [H] (at least 16), "
                             f"not a divisor: got {' '.join(map(str, args.resolution))}")
        resolution, scene = 1, _scene_config(args)
    else:
        if args.resolution is not None and len(args.resolution) != 1:
            raise InputError("-r/--resolution takes one divisor for a dataset folder (e.g. -r 4)")
        resolution, scene = (args.resolution[0] if args.resolution else d.resolution), SceneConfig()
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
    optim = dataclasses.replace(o, **opt_kw)
    dens_kw = {}
    if args.iterations is not None and args.iterations < o.iterations:
        # a shorter schedule keeps the paper's proportions (densify until half the run)
        dens_kw["densify_until_iter"] = min(dn.densify_until_iter, args.iterations // 2)
    densify = dataclasses.replace(dn, **dens_kw)
    save = tuple(i for i in TrainConfig().save_iterations if i < optim.iterations)
    return TrainConfig(data=data, optim=optim, densify=densify, scene=scene, seed=args.seed,
                       checkpoint_every=args.checkpoint_every, eval_every=args.eval_every, save_iterations=save)


RUN_OUTPUTS = ("checkpoints", "renders", "compare", "config.json", "metrics.json", "eval.json", "history.json",
               "curves.png", "gaussians.xml", "point_cloud.ply")


def _clear_run(out: Path) -> None:
    """Remove an earlier run's outputs from ``out`` (cached references stay)."""
    import shutil

    for name in RUN_OUTPUTS:
        p = out / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    for p in out.glob("point_cloud_*.ply"):
        p.unlink()


def _saved_cache(saved: dict, out: Path) -> str | None:
    """The cache folder of a run's references: OUTDIR/references when they are there (the folder may have moved),
    else the folder the run recorded."""
    refs = saved.get("references")
    if not refs:
        return None
    key = Path(refs).name
    return str(out / "references") if (out / "references" / key).is_dir() else str(Path(refs).parent)


def _saved_key(saved: dict | None) -> str | None:
    refs = (saved or {}).get("references")
    return Path(refs).name if refs else None


def cmd_optimize(args) -> int:
    from .config import TrainConfig
    from .optim.trainer import Trainer, TrainingDiverged

    out = Path(args.output)
    src = Path(args.scene)
    if not src.exists():
        raise InputError(f"{src}: not found")
    if args.resume and args.overwrite:
        raise InputError("give at most one of --resume and --overwrite")
    saved = None
    if args.resume and args.settings:
        raise InputError("--set cannot change a run being resumed (its settings are in OUTDIR/config.json)")
    if args.resume:
        cfg_path = out / "config.json"
        if not cfg_path.exists():
            raise InputError(f"{cfg_path}: nothing to resume (no config.json in the output folder)")
        saved = json.loads(cfg_path.read_text())
        cfg = TrainConfig.from_dict(saved["train"])
    else:
        if (out / "checkpoints").exists() and any((out / "checkpoints").iterdir()) and not args.overwrite:
            raise InputError(f"{out}: holds an earlier run (use --resume to continue it, --overwrite to start "
                             "again, or another folder)")
        cfg = _train_config(args, scene_file=_is_scene_file(src))
        try:
            cfg = cfg.with_settings(args.settings or ())
        except ValueError as e:
            raise InputError(str(e)) from None
    cache = args.cache or (_saved_cache(saved, out) if saved else None)
    # everything is checked (and references rendered) before an earlier run is removed
    ds = _load_input(src, cfg, out, cache=cache, progress=not args.quiet, expect_key=_saved_key(saved))
    if args.overwrite:
        _clear_run(out)
    trainer = Trainer(ds, cfg, out, progress=not args.quiet)
    try:
        metrics = trainer.run(resume=args.resume)
    except TrainingDiverged as e:
        print(f"mi-gs: error: {e}", file=sys.stderr)
        return 3
    if ds.layout == "mitsuba":
        from .data.mitsuba_scene import write_gaussian_scene

        cam = (ds.test or ds.train)[0].camera
        write_gaussian_scene(out / "gaussians.xml", "point_cloud.ply", cam, ds.color_space, ds.background)
    print(json.dumps({"output": str(out), **metrics["mean"], "gaussians": metrics["gaussians"],
                      "training_seconds": metrics["training_seconds"]}, indent=2))
    return 0


def _load_input(src: Path, cfg, out: Path, cache: str | None = None, progress: bool = True,
                expect_key: str | None = None):
    """The dataset of a scene folder, or of a Mitsuba scene file (references cached in ``cache`` or
    OUTDIR/references)."""
    d = cfg.data
    if _is_scene_file(src):
        from .data.mitsuba_scene import load_scene_dataset

        return load_scene_dataset(src, cfg.scene, cache_root=Path(cache) if cache else out / "references",
                                  background=d.background, test_every=d.test_every, seed=d.seed, progress=progress,
                                  log=lambda line: print(line, file=sys.stderr, flush=True), expect_key=expect_key)
    from .data.dataset import load_dataset

    return load_dataset(src, resolution=d.resolution, background=d.background, test_every=d.test_every,
                        random_points=d.random_points, seed=d.seed, masks=d.masks)


# ------------------------------------------------------------------------------------------------------ eval
def cmd_eval(args) -> int:
    from .config import TrainConfig
    from .data.dataset import load_dataset
    from .evaluate import evaluate_views, summarize
    from .model.gaussians import Gaussians
    from .report import write_json

    out = Path(args.run)
    cfg_path, ply = out / "config.json", out / "point_cloud.ply"
    for p in (cfg_path, ply):
        if not p.exists():
            raise InputError(f"{p}: missing (is {out} an mi-gs optimize output folder?)")
    saved = json.loads(cfg_path.read_text())
    cfg = TrainConfig.from_dict(saved["train"])
    d = cfg.data
    src = Path(args.dataset or saved["dataset"])
    if _is_scene_file(src):
        import dataclasses

        # the references cached by the run (rendered again only if they are gone); no initial points needed
        cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, init="random", init_points=1))
        ds = _load_input(src, cfg, out, cache=_saved_cache(saved, out), expect_key=_saved_key(saved))
    else:
        ds = load_dataset(src, resolution=d.resolution, background=d.background, test_every=d.test_every,
                          random_points=0, masks=d.masks)
    views = ds.test if ds.test else ds.train
    g = Gaussians.load_ply(ply)
    scores, note = evaluate_views(g, views, tuple(ds.background), cfg=cfg.raster, color_space=ds.color_space)
    result = {"split": "test" if ds.test else "train", "mean": summarize(scores),
              "views": {s.name: {"psnr": s.psnr, "ssim": s.ssim, **({"lpips": s.lpips} if s.lpips is not None
                                                                  else {})} for s in scores},
              "gaussians": g.n}
    if note:
        result["lpips_note"] = note
    write_json(out / "eval.json", result)
    print(json.dumps({"output": str(out / "eval.json"), **result["mean"], "gaussians": g.n,
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
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mi-gs", description="3D Gaussian Splatting as a Mitsuba 3 plugin.")
    p.add_argument("--variant", default=None, help="Mitsuba variant (default: cuda_ad_rgb if available, else llvm_ad_rgb)")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("info", help="summarize a 3DGS .ply, a dataset folder or a Mitsuba scene .xml")
    s.add_argument("path")
    s.add_argument("-r", "--resolution", type=int, default=1, help="dataset resolution divisor")
    s.set_defaults(func=cmd_info)

    s = sub.add_parser("render", help="render a 3DGS .ply (from a camera JSON or a dataset's views) or a scene .xml")
    s.add_argument("input", help="model.ply or scene.xml")
    s.add_argument("--camera", help="camera JSON (see README)")
    s.add_argument("--dataset", help="dataset folder whose views to render")
    s.add_argument("--split", choices=("train", "test", "all"), default="test")
    s.add_argument("-o", "--output", required=True, help="output .exr/.png file, or folder with --dataset")
    s.add_argument("-r", "--resolution", type=int, default=1)
    s.add_argument("--background", type=float, nargs="+", default=None, help="background colour (1 or 3 values)")
    s.add_argument("--sh-degree", type=int, default=None, help="active SH degree (default: the model's)")
    s.add_argument("--color-space", choices=("srgb", "linear"), default="srgb",
                   help="what the model's colours are (3DGS models trained on photos: srgb)")
    s.add_argument("--alpha", action="store_true", help="write an alpha channel")
    s.add_argument("--spp", type=int, default=None, help="samples per pixel (scene .xml only)")
    s.add_argument("--sensor", type=int, default=0, help="sensor index (scene .xml only)")
    s.add_argument("-D", "--define", action="append", default=None, metavar="KEY=VALUE",
                   help="set a scene parameter (scene .xml only), as mitsuba -D; repeatable")
    s.set_defaults(func=cmd_render)

    s = sub.add_parser("optimize", help="fit Gaussians to a COLMAP / Blender / instant-ngp scene folder, or to "
                                        "path-traced references of a Mitsuba scene .xml")
    s.add_argument("scene", help="scene folder, or Mitsuba scene file (.xml)")
    s.add_argument("-o", "--output", required=True, help="output folder")
    s.add_argument("--iterations", type=int, default=None, help="default 30000 (the paper's)")
    s.add_argument("-r", "--resolution", type=int, nargs="+", default=None,
                   help="scene folder: divide the image size by this (default 1); scene .xml: the film size of "
                        "generated cameras, W [H] (default: the scene's sensor's, else 256)")
    s.add_argument("--white-background", action="store_true", help="composite RGBA images over white")
    s.add_argument("--background", type=float, nargs="+", default=None, help="background colour (1 or 3 values)")
    s.add_argument("--random-background", action="store_true", help="random background colour per iteration")
    s.add_argument("--sh-degree", type=int, default=None, help="maximum SH degree (default 3)")
    s.add_argument("--test-every", type=int, default=8, help="hold out every N-th image (COLMAP/ngp; 0: none)")
    s.add_argument("--random-points", type=int, default=None,
                   help="initial random points for layouts without SfM points (default 100000)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--set", action="append", default=None, metavar="SECTION.FIELD=VALUE", dest="settings",
                   help="set any field of the training configuration (mi_gaussians/config.py), applied after the "
                        "other options, e.g. --set densify.min_opacity=0.1 --set optim.feature_lr=0.005; repeatable")
    s.add_argument("--checkpoint-every", type=int, default=1000)
    s.add_argument("--eval-every", type=int, default=1000, help="test PSNR for the curves every N iterations")
    s.add_argument("--resume", action="store_true", help="continue the run saved in the output folder")
    s.add_argument("--overwrite", action="store_true",
                   help="start a new run in an output folder that holds one (cached references are kept)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    g = s.add_argument_group("Mitsuba scene (.xml) input")
    g.add_argument("--rig", choices=("auto", "sensors", "hemisphere", "sphere"), default=None,
                   help="cameras: the scene's sensors, or generated around its bounding box (default auto: the "
                        "sensors if the scene declares several, else hemisphere)")
    g.add_argument("--views", type=int, default=None, help="generated training cameras (default 64; --seed also "
                                                           "picks the rig, so another seed renders new references)")
    g.add_argument("--test-views", type=int, default=None, help="generated held-out cameras (default 8)")
    g.add_argument("--radius", type=float, default=None,
                   help="rig radius (default: the bounding sphere fills the view)")
    g.add_argument("--fov", type=float, default=None, help="horizontal field of view in degrees (default: the "
                                                           "sensor's, else 40)")
    g.add_argument("--up", type=float, nargs=3, default=None, help="world up (default: the sensor's, else 0 1 0)")
    g.add_argument("--spp", type=int, default=None, help="reference samples per pixel (default: the sensor's, "
                                                         "else 128)")
    g.add_argument("--linear", action="store_true",
                   help="train on linear radiance (default: on the sRGB-encoded references)")
    g.add_argument("--init", choices=("shapes", "random", "sfm"), default=None,
                   help="initial points: sampled on the shapes and coloured by the references (default), random "
                        "in the bounding box, or structure from motion")
    g.add_argument("--init-points", type=int, default=None, help="initial points for shapes/random (default 50000)")
    g.add_argument("--cache", default=None, help="folder for the cached references (default OUTDIR/references)")
    g.add_argument("-D", "--define", action="append", default=None, metavar="KEY=VALUE",
                   help="set a scene parameter (<default name=\"KEY\">), as mitsuba -D; repeatable")
    s.set_defaults(func=cmd_optimize)

    s = sub.add_parser("eval", help="recompute the metrics of a saved run on its test views")
    s.add_argument("run", help="an mi-gs optimize output folder")
    s.add_argument("--dataset", default=None, help="dataset folder (default: the one the run was trained on)")
    s.set_defaults(func=cmd_eval)

    s = sub.add_parser("convert", help="structure-from-motion with pycolmap: images folder -> COLMAP scene")
    s.add_argument("images", help="folder of input images")
    s.add_argument("-o", "--output", required=True, help="scene folder to create (images/ + sparse/0)")
    s.add_argument("--camera-model", default="OPENCV")
    s.add_argument("--resize", action="store_true", help="also write images_2/4/8")
    s.add_argument("--overwrite", action="store_true")
    s.add_argument("--threads", type=int, default=-1)
    s.add_argument("--max-image-size", type=int, default=3200)
    s.set_defaults(func=cmd_convert)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        _set_variant(args.variant)
        import mi_gaussians  # noqa: F401  (registers the plugins for the variant)

        return args.func(args)
    except (InputError, ValueError, FileNotFoundError, NotADirectoryError, PermissionError) as e:
        print(f"mi-gs: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_INPUT_ERROR
    except RuntimeError as e:   # Mitsuba reports scene-file problems as RuntimeError
        print(f"mi-gs: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_INPUT_ERROR
    except KeyboardInterrupt:
        print("mi-gs: interrupted", file=sys.stderr)
        return 130


def _one_line(e: BaseException) -> str:
    # Dr.Jit/Mitsuba wrap errors raised inside custom operations ("... (see above)"): report the innermost cause
    while (e.__cause__ or e.__context__) is not None and "see above" in str(e):
        e = e.__cause__ or e.__context__
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return " ".join(lines) if len(lines) <= 3 else " ".join(lines[:3]) + " ..."


if __name__ == "__main__":
    sys.exit(main())
