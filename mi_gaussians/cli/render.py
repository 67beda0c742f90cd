"""``mi-gs render``: a model (.ply, .splat, .spz, .glb, .gltf) from a camera JSON or from a dataset's views, or any
Mitsuba scene (.xml) with its own integrator."""

from __future__ import annotations

import os
from pathlib import Path

from ..memory import check_image

from .args import (add_background, add_define, add_model_input, add_output, background, existing, is_model,
                   model_suffixes, non_negative_int, positive_int, sh_degree)
from .errors import InputError, note, warn


def add_parser(sub) -> None:
    from ..config import DataConfig

    s = sub.add_parser("render", help="render a model (.ply, .splat, .spz, .glb, .gltf; from a camera JSON or a "
                                      "dataset's views) or a scene .xml")
    add_model_input(s, "model.ply|.splat|.spz|.glb|.gltf or scene.xml",
                    antialiased="render with Mip-Splatting's 2D filter (default: as the run whose config.json sits "
                                "beside the model was trained, or as an .spz file records, else off)")
    s.add_argument("--camera", help="camera JSON (see README)")
    s.add_argument("--dataset", help="dataset folder whose views to render")
    s.add_argument("--split", choices=("train", "test", "all"), default="test")
    add_output(s, "output .exr/.png file, or folder with --dataset", overwrite="replace existing output files")
    s.add_argument("-r", "--resolution", type=positive_int, default=None,
                   help=f"with --dataset: divide its image size by this (default {DataConfig().resolution})")
    add_background(s, "background colour (1 or 3 values)")
    s.add_argument("--sh-degree", type=sh_degree, default=None, help="active SH degree (default: the model's)")
    s.add_argument("--color-space", choices=("srgb", "linear"), default="srgb",
                   help="what the model's colours are (3DGS models trained on photos: srgb)")
    s.add_argument("--alpha", action="store_true", help="write an alpha channel")
    s.add_argument("--spp", type=positive_int, default=None, help="samples per pixel (scene .xml only)")
    s.add_argument("--sensor", type=non_negative_int, default=0, help="sensor index (scene .xml only)")
    add_define(s, "set a scene parameter (scene .xml only), as mitsuba -D; repeatable")


def run(args) -> int:
    src = existing(args.input)
    out = Path(args.output)
    if src.suffix.lower() == ".xml":
        return _render_scene_file(args, src, out)
    if not is_model(src):
        raise InputError(f"{src}: expected a model ({', '.join(model_suffixes())}) or a Mitsuba scene .xml")
    if (args.camera is None) == (args.dataset is None):
        raise InputError("give exactly one of --camera CAM.json or --dataset DIR")
    if args.dataset is not None:
        return _render_dataset_views(args, out)
    if args.resolution is not None:
        raise InputError("-r/--resolution applies to --dataset only (with --camera, the camera JSON gives the "
                         "image size)")
    from ..data.camera import Camera

    outputs = _outputs_for(out, args.overwrite)
    cam = Camera.from_json(args.camera)
    check_image(cam.width, cam.height, args.camera, advice="give the camera a smaller width and height")
    _render_views(args, [(cam.name or "view", cam)], args.color_space, [outputs])
    print(out)
    return 0


def _render_views(args, views, color_space: str, out_paths, bg=None) -> None:
    import numpy as np
    from tqdm import tqdm

    from ..imwrite import write_image
    from ..model.gaussians import Gaussians
    from ..raster.rasterize import render
    from ..runs import model_raster_config

    g = Gaussians.load(args.input)
    bg = background(args.background) if bg is None else bg
    cfg = model_raster_config(args.input, args.antialiased, warn=warn)
    for (name, cam), outs in tqdm(list(zip(views, out_paths)), desc="render", unit="view", disable=len(views) < 2):
        out = render(g, cam, background=bg, sh_degree=args.sh_degree, cfg=cfg)
        rgb = np.array(out.rgb, dtype=np.float32)
        if args.alpha:
            rgb = np.concatenate([rgb, np.array(out.alpha, dtype=np.float32)[..., None]], axis=-1)
        for p in outs:
            write_image(p, rgb, color_space)


def _outputs_for(path: Path, overwrite: bool) -> list[Path]:
    from ..io_utils import check_output_file, remove_stale_temporary_files

    ext = path.suffix.lower()
    if ext not in (".exr", ".png"):
        raise InputError(f"{path}: unsupported output format {ext or '(none)'} (use .exr or .png)")
    check_output_file(path)
    _check_new([path], overwrite)
    remove_stale_temporary_files(path.parent)
    return [path]


def _check_new(paths, overwrite: bool) -> None:
    """Outputs are not written over existing files (or links) unless ``--overwrite`` says so."""
    for p in paths:
        if os.path.lexists(p) and not overwrite:
            raise InputError(f"{p}: exists (give --overwrite to replace it)")


def _render_scene_file(args, src: Path, out: Path) -> int:
    """A Mitsuba scene .xml rendered by Mitsuba with its own integrator (linear outputs)."""
    import mitsuba as mi
    import numpy as np

    from ..data.scene_file import load_file
    from ..imwrite import write_image

    if args.antialiased is not None:
        raise InputError(f"--{'' if args.antialiased else 'no-'}antialiased applies to a .ply; in a scene .xml the "
                         "gaussian_splatting integrator's antialiased parameter decides")
    outputs = _outputs_for(out, args.overwrite)
    scene = load_file(src, args.define)
    if not scene.sensors():
        raise InputError(f"{src}: the scene has no sensor")
    if args.sensor >= len(scene.sensors()):
        raise InputError(f"{src}: sensor index {args.sensor} out of range ({len(scene.sensors())} sensors)")
    width, height = scene.sensors()[args.sensor].film().crop_size()
    check_image(width, height, f"{src} (sensor {args.sensor}'s film)", advice="give the film a smaller size")
    img = np.array(mi.render(scene, sensor=args.sensor, spp=args.spp or 0), dtype=np.float32)
    for p in outputs:
        write_image(p, img[..., :4] if img.shape[-1] >= 4 else img[..., :3], "linear")
        print(p)
    return 0


def _render_dataset_views(args, out: Path) -> int:
    """A model rendered from the views of a dataset folder into the folder ``out`` (EXR and PNG per view)."""
    from ..data.dataset import load_dataset
    from ..io_utils import check_output_folder, remove_stale_temporary_files
    from ..runs import check_outside_dataset

    check_outside_dataset(args.dataset, out)
    resolution, bg = _as_the_run(args)
    ds = load_dataset(args.dataset, resolution=resolution, background=bg)
    if args.split != "test":
        from ..runs import model_run_cameras

        ds = model_run_cameras(args.input, ds)
    views = {"train": ds.train, "test": ds.test, "all": ds.views}[args.split]
    if not views:
        raise InputError(f"{args.dataset}: the {args.split} split is empty")
    largest = max(views, key=lambda v: v.camera.width * v.camera.height).camera
    check_image(largest.width, largest.height, args.dataset, advice="render at a larger -r divisor")
    if out.suffix:
        raise InputError(f"{out}: with --dataset, -o names an output folder")
    check_output_folder(out)
    paths = [[out / f"{Path(v.name).stem}.exr", out / f"{Path(v.name).stem}.png"] for v in views]
    _check_new([p for ps in paths for p in ps], args.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    remove_stale_temporary_files(out)
    _render_views(args, [(v.name, v.camera) for v in views], ds.color_space, paths, bg)
    print(f"{len(views)} views -> {out}")
    return 0


def _as_the_run(args) -> tuple[int, tuple]:
    """The resolution divisor and background of ``render --dataset``: those given, else, for a model in a run folder
    trained on this dataset, the run's (as ``view`` takes them; said in a note), else the defaults."""
    from .. import run_folder
    from ..config import DataConfig

    resolution = args.resolution or DataConfig().resolution
    bg = background(args.background)
    folder = Path(args.input).parent
    if (args.resolution is not None and args.background is not None) or not (folder / run_folder.CONFIG).is_file():
        return resolution, bg
    try:
        record = run_folder.RunRecord.read(folder, "")
    except ValueError:
        return resolution, bg
    if Path(record.dataset).resolve() != Path(args.dataset).resolve():
        return resolution, bg
    d = record.train.data
    taken = []
    if args.resolution is None and d.resolution != resolution:
        resolution = d.resolution
        taken.append(f"-r {d.resolution}")
    if args.background is None and tuple(d.background) != bg:
        bg = tuple(float(b) for b in d.background)
        taken.append(f"--background {' '.join(f'{b:g}' for b in bg)}")
    if taken:
        note(f"rendering as the run in {folder} was trained ({', '.join(taken)}; give the options to choose "
             "otherwise)")
    return resolution, bg
