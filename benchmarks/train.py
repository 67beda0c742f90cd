"""Training benchmark: test PSNR / SSIM / Gaussians / minutes at milestones, and seconds per iteration against the
number of Gaussians (to read off the comparison with OpenSplat's CPU build).

    python benchmarks/train.py mi_objects_blender --milestones 7000 30000
    python benchmarks/train.py mi_objects_colmap --milestones 2000 7000 30000   # 2000 of 30k: vs OpenSplat
    python benchmarks/train.py fox maryrose --milestones 7000
    python benchmarks/train.py mi_objects_colmap_black --milestones 2000 --schedule 30000

Datasets are read from ../shared/data (next to the repository). Outputs go to --out (default /tmp/mi_gs_bench).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = (ROOT / ".." / "shared" / "data").resolve()

# name -> (folder, resolution divisor, background, what to say about it)
DATASETS = {
    "mi_objects_blender": ("mi_objects/blender", 1, (1.0, 1.0, 1.0), "200x200, white background"),
    # the colmap images are the RGBA renders composited over white (the dataset's README), so the empty sky is
    # the background colour, as with 3DGS's --white_background; "_black" is the 3DGS default for COLMAP input
    "mi_objects_colmap": ("mi_objects/colmap", 1, (1.0, 1.0, 1.0), "200x200, SfM points, white background"),
    "mi_objects_colmap_black": ("mi_objects/colmap", 1, (0.0, 0.0, 0.0), "200x200, SfM points, black background"),
    "mi_room_colmap": ("mi_room/colmap", 1, (0.0, 0.0, 0.0), "256x256, SfM points"),
    "fox": ("fox", 4, (0.0, 0.0, 0.0), "-r 4: 267x474 after undistortion, points triangulated from the posed images"),
    "maryrose": ("maryrose", 8, (1.0, 1.0, 1.0), "-r 8: 432x432 after undistortion, masked (masks/), SfM points"),
}


def run_one(name: str, milestones: list[int], out_root: Path, variant: str, schedule: int | None = None,
            freeze: bool = True, settings: tuple = ()) -> list[dict]:
    import mitsuba as mi

    mi.set_variant(variant)
    import mi_gaussians as mig
    from mi_gaussians.config import DataConfig, TrainConfig
    from mi_gaussians.evaluate import evaluate_views, summarize
    from mi_gaussians.optim.trainer import Trainer
    from mi_gaussians.runs import training_dataset

    folder, res, bg, note = DATASETS[name]
    path = DATA / folder
    if not path.exists():
        print(f"{name}: {path} missing, skipped", file=sys.stderr)
        return []
    iters = max(milestones)
    # the learning-rate decay and densification of a `schedule`-iteration run, stopped at the last milestone
    schedule = max(schedule or iters, iters)
    base = TrainConfig(data=DataConfig(resolution=res, background=bg), checkpoint_every=1000, eval_every=1000,
                       save_iterations=tuple(milestones)).with_iterations(schedule)
    cfg = dataclasses.replace(base, optim=dataclasses.replace(base.optim, iterations=iters),
                              save_iterations=tuple(milestones), freeze=freeze).with_settings(settings)
    out = out_root / (name if schedule == iters else f"{name}_of_{schedule}")
    # (the points `mi-gs optimize` starts from: the layout's own, else triangulated from the posed images)
    ds = training_dataset(path, cfg, out, progress=False, log=lambda line: print(line, file=sys.stderr))
    tr = Trainer(ds, cfg, out, progress=True)
    metrics = tr.run(resume=(out / "checkpoints" / "ckpt.npz").exists())
    h = tr.history
    rows = []
    for m in milestones:
        ply = out / ("point_cloud.ply" if m == iters else f"point_cloud_{m}.ply")
        g = mig.Gaussians.load_ply(ply)
        scores, _ = evaluate_views(g, ds.test, tuple(ds.background), cfg=cfg.raster, with_lpips=False,
                                   color_space=ds.color_space)
        s = summarize(scores)
        k = h.iteration.index(m)
        # seconds per iteration around the milestone (the last 200 iterations before it)
        k0 = max(0, k - 200)
        spi = (h.seconds[k] - h.seconds[k0]) / max(1, k - k0)
        rows.append({"dataset": name, "note": note, "iterations": m, "psnr": s["psnr"], "ssim": s["ssim"],
                     "gaussians": g.n, "minutes": h.seconds[k] / 60.0, "sec_per_iter": spi})
    # seconds per iteration against the number of Gaussians (binned; the mean: frozen iterations are committed, and
    # their time recorded, SYNC_EVERY at a time)
    n = np.asarray(h.gaussians)
    t = np.diff(np.asarray([0.0] + h.seconds))
    print(f"\n{name}: seconds per iteration vs Gaussians")
    print("| Gaussians | ms / iteration |\n|---:|---:|")
    edges = np.unique(np.quantile(n, np.linspace(0, 1, 9)).astype(int))
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (n >= lo) & (n <= hi)
        if sel.sum() > 20:
            print(f"| {int(np.median(n[sel])):,} | {1e3 * np.mean(t[sel]):.2f} |")
    print_split(name, metrics["loop"], metrics["training_seconds"])
    (out / "bench.json").write_text(json.dumps({"milestones": rows, "loop": metrics["loop"]}, indent=2))
    return rows


#: what each part of the time split (mi_gaussians.optim.loop_state.TIME_PARTS) holds
PARTS = {"frozen": "frozen steps replayed", "recording": "frozen steps that recorded (trace, record, compile)",
         "waiting": "waiting for queued frozen steps", "traced": "traced iterations (the first, refinement ones)",
         "refinement": "refinements (densify, prune, reset)", "other": "the rest of the loop"}


def print_split(name: str, loop: dict, training_seconds: float) -> None:
    """Where a run's training time went (metrics.json's "loop")."""
    print(f"\n{name}: the training time, {training_seconds / 60:.1f} minutes, by part")
    print("| part | seconds | share |\n|---|---:|---:|")
    for part, seconds in loop["seconds"].items():
        print(f"| {PARTS.get(part, part)} | {seconds:.1f} | {100 * seconds / max(training_seconds, 1e-9):.1f} % |")
    print(f"recordings {loop['recordings']}, kernels built {loop.get('compiles', '?')} (and "
          f"{loop.get('cache_loads', '?')} loaded from the kernel cache), overflows {loop['overflows']} "
          f"({loop['replayed']} iterations replayed), traced iterations {loop['traced']}, refinements {loop['refinements']}, syncs {loop['syncs']}; outside the "
          f"training time: evaluation {loop['outside']['evaluation']:.1f} s, saving {loop['outside']['saving']:.1f} s; "
          f"iterations by the blend's pixels per lane: {loop.get('lanes', '?')}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+", choices=sorted(DATASETS))
    ap.add_argument("--milestones", type=int, nargs="+", default=[7000, 30000])
    ap.add_argument("--out", default="/tmp/mi_gs_bench")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--schedule", type=int, default=None,
                    help="use the learning-rate and densification schedule of this many iterations "
                         "(default: the last milestone), e.g. 30000 to compare with iteration 2000 of a 30k run")
    ap.add_argument("--loop", choices=("frozen", "traced"), default="frozen",
                    help="the training step: frozen (the default) or traced (--set freeze=false)")
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                    help="a training setting, as mi-gs optimize's --set (e.g. row_classes=4)")
    args = ap.parse_args(argv)
    rows = []
    for name in args.datasets:
        rows += run_one(name, sorted(args.milestones), Path(args.out), args.variant, args.schedule,
                        args.loop == "frozen", tuple(args.settings))
    print("\n| dataset | iterations | test PSNR | test SSIM | Gaussians | minutes | s / it (at milestone) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['dataset']} ({r['note']}) | {r['iterations']:,} | {r['psnr']:.2f} | {r['ssim']:.4f} "
              f"| {r['gaussians']:,} | {r['minutes']:.2f} | {r['sec_per_iter']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
