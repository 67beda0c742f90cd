"""``mi-gs info PATH``: a summary of a model (.ply), a dataset folder or a Mitsuba scene (.xml), as JSON."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from .args import add_define, existing, positive_int
from .errors import InputError


def add_parser(sub) -> None:
    from ..config import DataConfig

    s = sub.add_parser("info", help="summarize a 3DGS .ply, a dataset folder or a Mitsuba scene .xml")
    s.add_argument("path")
    s.add_argument("-r", "--resolution", type=positive_int, default=DataConfig().resolution,
                   help="dataset resolution divisor")
    add_define(s, "set a scene parameter (scene .xml only), as mitsuba -D; repeatable")


def run(args) -> int:
    path = existing(args.path)
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


def _ply_info(path: Path) -> dict:
    import numpy as np

    from ..conventions import sh_degree_from_coeff_count, sigmoid
    from ..model.ply import read_ply
    from ..model.point_ply import is_point_cloud, read_points

    if is_point_cloud(path):
        xyz, _ = read_points(path)
        return {"file": str(path), "points": int(len(xyz)),
                **({"bbox_min": xyz.min(0).round(4).tolist(), "bbox_max": xyz.max(0).round(4).tolist()}
                   if len(xyz) else {})}

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
    from ..data.scene_file import load_file

    scene = load_file(path, defines)
    return {"file": str(path), "integrator": scene.integrator().class_name() if scene.integrator() else None,
            "sensors": [s.id() or s.class_name() for s in scene.sensors()],
            "shapes": len(scene.shapes()), "bbox": [list(scene.bbox().min), list(scene.bbox().max)]}


def _dataset_info(path: Path, resolution: int) -> dict:
    from ..data.dataset import load_dataset, unreadable_images

    ds = load_dataset(path, resolution=resolution)
    unreadable = unreadable_images(ds.views, progress=sys.stderr.isatty())
    cam = ds.train[0].camera
    return {"dataset": str(path), "layout": ds.layout, "train_views": len(ds.train), "test_views": len(ds.test),
            "image_size": [cam.width, cam.height], "fx": round(cam.fx, 4), "fy": round(cam.fy, 4),
            "cx": round(cam.cx, 4), "cy": round(cam.cy, 4), "color_space": ds.color_space,
            "points": 0 if ds.points_xyz is None else int(ds.points_xyz.shape[0]),
            "extent": round(ds.extent, 6), "images_checked": len(ds.views), "unreadable_images": unreadable}
