"""``mi-gs convert IMAGES -o SCENE``: structure from motion with pycolmap into a COLMAP scene folder."""

from __future__ import annotations

import json

from .args import add_output, positive_int
from .errors import warn


def add_parser(sub) -> None:
    from ..config import ConvertConfig

    c = ConvertConfig()
    s = sub.add_parser("convert", help="structure-from-motion with pycolmap: images folder -> COLMAP scene")
    s.add_argument("images", help="folder of input images")
    add_output(s, "scene folder to create (images/ + sparse/0)",
               overwrite="replace an earlier result in the scene folder (only the folders convert writes)")
    s.add_argument("--camera-model", default=c.camera_model, help=f"COLMAP camera model (default {c.camera_model})")
    s.add_argument("--resize", action="store_true", default=c.resize, help="also write images_2/4/8")
    s.add_argument("--threads", type=int, default=c.num_threads, help="threads (default -1: all cores)")
    s.add_argument("--max-image-size", type=positive_int, default=c.max_image_size,
                   help=f"SIFT extraction downscales larger images (default {c.max_image_size})")


def run(args) -> int:
    from ..data.convert import convert

    res = convert(args.images, args.output, camera_model=args.camera_model, resize=args.resize,
                  overwrite=args.overwrite, num_threads=args.threads, max_image_size=args.max_image_size,
                  progress=lambda line: print(line, flush=True))
    problems = res.problems()
    print(json.dumps({"scene": str(res.out_dir), "images": res.num_images, "registered": res.num_registered,
                      "points": res.num_points, "mean_reprojection_error_px": round(res.mean_reprojection_error, 4),
                      "fx": round(res.focal[0], 4), "fy": round(res.focal[1], 4),
                      **({"problems": problems} if problems else {})}, indent=2), flush=True)
    for line in problems:
        warn(f"{res.out_dir}: {line}")
    return 0
