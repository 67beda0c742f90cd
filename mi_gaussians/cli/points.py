"""``mi-gs points DATASET -o points.ply``: the initial points a run of ``mi-gs optimize DATASET`` with the same options
would start from (the dataset's own, triangulated from its posed images, random, or sampled on a scene's shapes), as a
point-cloud PLY to look at (``mi-gs view points.ply``) or to use elsewhere."""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from . import train_options
from .args import add_output, existing
from .errors import InputError


def add_parser(sub) -> None:
    s = sub.add_parser("points", help="write the point cloud a run would start from (the dataset's own, triangulated "
                                      "from its posed images, random, or sampled on a scene's shapes) as a PLY")
    s.add_argument("dataset", help="dataset folder, or Mitsuba scene file (.xml)")
    add_output(s, "the point-cloud .ply to write", overwrite="replace an existing file")
    groups = train_options.add_arguments(s)
    s.add_argument("--set", action="append", default=None, metavar="SECTION.FIELD=VALUE", dest="settings",
                   help="set any field of the training configuration, as mi-gs optimize --set; repeatable")
    groups["scene"].add_argument("--cache", default=None,
                                 help="keep the work (triangulations, a scene's references) in this folder and reuse "
                                      "it (give a run's output folder to reuse its own; default: a temporary folder)")
    s.add_argument("--quiet", action="store_true", help="no progress bar and no information lines (warnings stay)")


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def run(args) -> int:
    from ..data.scene_file import is_scene_file
    from ..io_utils import check_output_file
    from ..model.point_ply import write_points
    from ..runs import check_outside_dataset, quiet, training_dataset

    src, out = existing(args.dataset), Path(args.output)
    if out.suffix.lower() != ".ply":
        raise InputError(f"{out}: a point cloud is written as .ply")
    check_output_file(out)
    check_outside_dataset(src, out)
    if args.cache is not None:
        check_outside_dataset(src, args.cache, "--cache")
    if out.exists() and not args.overwrite:
        raise InputError(f"{out}: exists (give --overwrite to replace it)")
    cfg = train_options.new_run_config(args, is_scene_file(src))
    with tempfile.TemporaryDirectory(prefix="mi-gs-points-") as scratch:
        ds = training_dataset(src, cfg, scratch, cache=args.cache or scratch, progress=not args.quiet,
                                log=quiet(_say) if args.quiet else _say)
    if ds.points_xyz is None or not len(ds.points_xyz):
        raise InputError(f"{src}: no initial points (data.random_points is 0 and the dataset has none)")
    write_points(out, ds.points_xyz, ds.points_rgb)
    print(json.dumps({"output": str(out), "points": int(len(ds.points_xyz)), "from": ds.points_from}, indent=2))
    return 0
