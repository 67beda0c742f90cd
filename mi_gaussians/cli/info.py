"""``mi-gs info PATH``: a summary of a model (.ply, .splat, .spz, .glb, .gltf), a run folder, a dataset folder or a
Mitsuba scene (.xml), as JSON."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from .args import add_define, existing, model_suffixes, positive_int
from .errors import InputError, warn


def add_parser(sub) -> None:
    from ..config import DataConfig

    s = sub.add_parser("info", help="summarize a 3DGS model (.ply, .splat, .spz, .glb, .gltf), a run folder (mi-gs "
                                    "optimize -o), a dataset folder or a Mitsuba scene .xml")
    s.add_argument("path")
    s.add_argument("-r", "--resolution", type=positive_int, default=DataConfig().resolution,
                   help="dataset resolution divisor")
    add_define(s, "set a scene parameter (scene .xml only), as mitsuba -D; repeatable")


def run(args) -> int:
    from ..run_folder import CONFIG

    path = existing(args.path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        info = _ply_info(path)
    elif suffix in model_suffixes():
        info = _web_info(path)
    elif suffix == ".xml":
        info = _scene_info(path, args.define)
    elif path.is_dir() and (path / CONFIG).is_file():
        info = _run_info(path)
    else:
        info = _dataset_info(path, args.resolution)
    print(json.dumps(info, indent=2))
    bad = info.get("unreadable_images")
    if bad:
        sys.stdout.flush()
        raise InputError(f"{path}: {len(bad)} of {info['images_checked']} images cannot be read (listed above under "
                         f"unreadable_images), e.g. {bad[0]}")
    return 0


def _ply_info(path: Path) -> dict:
    from ..model.ply import read_ply
    from ..model.point_ply import is_point_cloud, read_points

    if is_point_cloud(path):
        xyz, _ = read_points(path)
        return {"file": str(path), "points": int(len(xyz)),
                **({"bbox_min": xyz.min(0).round(4).tolist(), "bbox_max": xyz.max(0).round(4).tolist()}
                   if len(xyz) else {})}

    return _model_info(path, read_ply(path))


def _model_info(path: Path, p: dict, **extra) -> dict:
    """The summary of a model's raw parameters (as ``read_ply`` gives them)."""
    import numpy as np

    from ..conventions import sh_degree_from_coeff_count, sigmoid

    n = p["means"].shape[0]
    info = {"file": str(path), "gaussians": n, "sh_degree": sh_degree_from_coeff_count(p["sh_rest"].shape[1] + 1),
            **extra}
    if n:
        opac = sigmoid(p["opacities"].astype(np.float64))
        sig = np.exp(p["scales"].astype(np.float64)).max(axis=1)
        info.update(bbox_min=p["means"].min(0).round(4).tolist(), bbox_max=p["means"].max(0).round(4).tolist(),
                    opacity_mean=round(float(opac.mean()), 4),
                    sigma_max_median=float(np.median(sig)))
    return info


def _web_info(path: Path) -> dict:
    """A model file of another format than PLY: its summary and what the file says beside the Gaussians."""
    from ..model.web_formats import read_model_info

    params, meta = read_model_info(path)
    return _model_info(path, params, **meta)


def _run_info(path: Path) -> dict:
    """A run folder: what it trains on, how far it got (its checkpoint), its final metrics when it finished, and its
    model."""
    import json
    import zipfile

    import numpy as np

    from ..run_folder import CHECKPOINT, METRICS, MODEL, RunRecord

    record = RunRecord.read(path, "not readable")
    cfg = record.train
    info = {"run": str(path), "dataset": record.dataset, "iterations": cfg.optim.iterations,
            "strategy": cfg.strategy, "finished": (path / METRICS).is_file() and (path / MODEL).is_file()}
    if (path / CHECKPOINT).is_file():
        try:
            with np.load(path / CHECKPOINT) as z:
                meta = json.loads(bytes(z["meta"]).decode())
                info["checkpoint"] = {"iteration": int(meta["step"]), "gaussians": int(z["param/means"].shape[0])}
        except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as e:
            why = " ".join(str(e).split())[:120] or type(e).__name__
            info["checkpoint"] = {"error": f"{path / CHECKPOINT}: not readable ({why})"}
    if (path / METRICS).is_file():
        try:
            m = json.loads((path / METRICS).read_text())
            info["test"] = {k: m["mean"][k] for k in ("psnr", "ssim", "lpips") if k in m.get("mean", {})}
            info["training_seconds"] = m.get("training_seconds")
        except (OSError, ValueError, TypeError, AttributeError):
            info["test"] = {"error": f"{path / METRICS}: not readable"}
    if (path / MODEL).is_file():
        info["model"] = _ply_info(path / MODEL)
    return info


def _scene_info(path: Path, defines) -> dict:
    from ..data.scene_file import load_file

    scene = load_file(path, defines)
    return {"file": str(path), "integrator": scene.integrator().class_name() if scene.integrator() else None,
            "sensors": [s.id() or s.class_name() for s in scene.sensors()],
            "shapes": len(scene.shapes()), "bbox": [list(scene.bbox().min), list(scene.bbox().max)]}


def _dataset_info(path: Path, resolution: int) -> dict:
    """A dataset folder: its views, first camera, points and lengths, and every image decoded once (with a progress
    bar on stderr: a large dataset takes minutes). Lengths, each under its own name: ``camera_spread`` (1.1 x the
    training cameras' largest distance from their mean: the reference's "extent", what pose errors are fractions
    of) and ``length_scale`` (what a run's position rates and size rules are fractions of, by the default
    ``data.extent``: metrics.json's ``extent``); ``extent`` and ``scene_extent``, their earlier names, stay."""
    from ..config import DataConfig
    from ..data.camera import intrinsics_problem
    from ..data.dataset import load_dataset, unreadable_images
    from ..data.pointcloud import DegenerateScale

    ds = load_dataset(path, resolution=resolution)
    cam = ds.train[0].camera
    info = {"dataset": str(path), "layout": ds.layout, "train_views": len(ds.train), "test_views": len(ds.test),
            "image_size": [cam.width, cam.height], "fx": round(cam.fx, 4), "fy": round(cam.fy, 4),
            "cx": round(cam.cx, 4), "cy": round(cam.cy, 4), "color_space": ds.color_space,
            "points": 0 if ds.points_xyz is None else int(ds.points_xyz.shape[0])}
    problems = [p for v in ds.views if (p := intrinsics_problem(v.camera)) is not None]
    if problems:
        more = f" (and {len(problems) - 1} more views)" if len(problems) > 1 else ""
        info["camera_problem"] = problems[0] + more
        warn(f"{path}: {problems[0]}{more}")
    spread = ds.extent
    info.update(camera_spread=round(spread, 6), length_scale_rule=DataConfig().extent)
    try:
        scale, fallback = ds.scene_scale()
        info["length_scale"] = round(scale, 6)
        if fallback:
            info["length_scale_note"] = fallback
    except DegenerateScale as e:
        info["length_scale"] = None
        info["length_scale_problem"] = str(e)
    info.update(extent=info["camera_spread"], scene_extent=info["length_scale"])
    unreadable = unreadable_images(ds.views, progress=True)     # (the bar shows after a few seconds: on stderr)
    return {**info, "images_checked": len(ds.views), "unreadable_images": unreadable}
