"""``mi-gs eval RUN_DIR``: the metrics of a saved run, recomputed on its test views (``eval.json``)."""

from __future__ import annotations

import json
from pathlib import Path

from . import errors
from .errors import InputError


def add_parser(sub) -> None:
    s = sub.add_parser("eval", help="recompute the metrics of a saved run on its test views")
    s.add_argument("run", help="an mi-gs optimize output folder")
    s.add_argument("--dataset", default=None, help="dataset folder (default: the one the run was trained on)")
    s.add_argument("--overwrite", action="store_true", help="replace the run's eval.json")


def run(args) -> int:
    from .. import run_folder

    out = Path(args.run)
    run_folder.RunLock(out).check_free()            # (a run still writing its folder: said so, before anything else)
    for p in (out / run_folder.CONFIG, out / run_folder.MODEL):
        if not p.exists():
            raise InputError(f"{p}: missing (is {out} an mi-gs optimize output folder?)")
    record = run_folder.RunRecord.read(out, "missing")
    with run_folder.RunLock(out):                 # (not while a run is writing the folder)
        return _evaluate(args, out, record)


def _evaluate(args, out: Path, record) -> int:
    from .. import run_folder
    from ..evaluate import PROTOCOLS, evaluate_views, scores_report
    from ..model.gaussians import Gaussians
    from ..report import write_json
    from ..runs import run_dataset

    manifest = run_folder.Manifest(out)
    if (out / run_folder.EVAL).exists() and not args.overwrite:
        raise InputError(f"{out / run_folder.EVAL}: exists (give --overwrite to replace it)")
    manifest.check_free([run_folder.EVAL])
    ds = run_dataset(record, out, args.dataset)
    views = ds.test
    if not views:           # (as metrics.json: the first training view, through its refined camera when refined)
        views = ds.train[:1]
        errors.note(f"the run in {out} has no test views: scoring its first training view, {views[0].name}, as "
                    "metrics.json does")
    g = Gaussians.load_ply(out / run_folder.MODEL)
    scores, note = evaluate_views(g, views, tuple(ds.background), cfg=record.train.raster,
                                  color_space=ds.color_space)
    report = scores_report(scores, note)
    note = report.pop("lpips_note", None)
    half, _ = evaluate_views(g, views, tuple(ds.background), cfg=record.train.raster, color_space=ds.color_space,
                             protocol="half")
    result = {"split": "test" if ds.test else "train (no test views)", "protocol": PROTOCOLS["full"], **report,
              "half_image": {"protocol": PROTOCOLS["half"], **scores_report(half)}, "gaussians": g.n,
              **({"lpips_note": note} if note else {})}
    manifest.claim([run_folder.EVAL])
    write_json(out / run_folder.EVAL, result)
    print(json.dumps({"output": str(out / run_folder.EVAL), **result["mean"],
                      "half_image": result["half_image"]["mean"], "gaussians": g.n,
                      **({"lpips_note": note} if note else {})}, indent=2))
    return 0
