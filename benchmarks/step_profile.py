"""Where a training step's device time goes, on a finished run's model: the run resumed from its checkpoint for a few
frozen steps past its end, ``dr.kernel_history()`` recorded over them, kernels grouped by their width (what a kernel
runs over tells what it is: the blend's lanes, the model's rows, the instance list, the pixels).

    python benchmarks/step_profile.py RUN                 # a finished mi-gs optimize output folder
    python benchmarks/step_profile.py RUN --steps 60 --set optim.coarse_to_fine=off

The run's folder is not changed (its checkpoint is copied to a temporary folder). Steps are those of the run's last
iteration's schedule (no densification, full SH degree); their scale is the schedule's at that iteration. The wall
time per step is measured over ``--steps`` steps without the kernel history, then the kernels over as many with it
(until 2026-11-30 both came from the history's window, whose records cost the wall time 1.5-3 ms a step).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path


def classify(size: int, n: int, lanes: int, pixels: int, capacity: int | None) -> str:
    """A kernel's group by its width."""
    if size == lanes:
        return f"{lanes:,} (tiles x lanes: the blend's loops)"
    if size == n:
        return f"{n:,} (one per Gaussian: projection, SH, their AD backward, Adam)"
    if n and size % n == 0 and size // n in (3, 4, 45, 15, 24):
        return "3, 4 or 3 x (K-1) per Gaussian (Adam on vector parameters and SH bands)"
    if capacity and size == capacity:
        return f"{capacity:,} (the instance capacity: binning)"
    if size == pixels:
        return f"{pixels:,} (one per pixel)"
    return "other widths"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args(argv)
    import mitsuba as mi

    mi.set_variant(args.variant)
    import drjit as dr

    from mi_gaussians.optim.trainer import Trainer
    from mi_gaussians.raster.blend import lane_layout, slot_count
    from mi_gaussians.run_folder import CHECKPOINT, RunRecord
    from mi_gaussians.runs import training_dataset

    record = RunRecord.read(args.run, "is it an mi-gs optimize output folder?")
    cfg = record.train.with_settings(args.settings) if args.settings else record.train
    extra = 3 * args.steps + 10
    cfg = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, iterations=cfg.optim.iterations + extra),
                              eval_every=0, checkpoint_every=10 ** 9, save_iterations=())
    tmp = Path(tempfile.mkdtemp())
    try:
        (tmp / Path(CHECKPOINT).parent).mkdir(parents=True)
        shutil.copy(args.run / CHECKPOINT, tmp / CHECKPOINT)
        ds = training_dataset(record.dataset, cfg, tmp, cache=record.references_cache(args.run), progress=False,
                              with_points=False)
        tr = Trainer(ds, cfg, tmp, progress=False)
        tr.run_id = None
        tr.load_checkpoint()
        for _ in range(args.steps + 5):          # (warm: records and compiles)
            tr.advance()
        tr._drain()
        dr.sync_thread()
        # the wall time in a window of its own: Dr.Jit's kernel history keeps each launch's record, and the pages
        # it takes cost a third of a small model's step
        t0 = time.perf_counter()
        for _ in range(args.steps):
            tr.advance()
        tr._drain()
        dr.sync_thread()
        wall = time.perf_counter() - t0
        dr.kernel_history_clear()
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            for _ in range(args.steps):
                tr.advance()
            tr._drain()
            dr.sync_thread()
            history = dr.kernel_history()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    cam = tr.views.camera(0)
    layout = tr.layout or lane_layout()          # (the trainer's choice: raster.lanes)
    tiles_x, tiles_y = layout.tiles(cam.width, cam.height)
    lanes = slot_count(tiles_x, tiles_y, layout) * layout.lanes_per_tile
    groups = defaultdict(lambda: [0, 0.0])
    for h in history:
        kind = str(h["type"]).split(".")[-1]
        key = classify(int(h.get("size", 0)), tr.params.n, lanes, cam.width * cam.height, tr.capacity) \
            if kind == "JIT" else "sorts, memsets, reductions"
        groups[key][0] += 1
        groups[key][1] += h.get("execution_time", 0.0)
    total = sum(t for _, t in groups.values()) or 1.0
    n = args.steps
    print(f"{args.run.name}: {tr.params.n:,} Gaussians, {cam.width}x{cam.height}, {n} frozen steps: "
          f"{1000 * wall / n:.1f} ms per step wall, {total / n:.1f} ms in kernels\n")
    print("| kernels, by their width | launches per step | ms per step | share |\n|---|---:|---:|---:|")
    for key, (count, t) in sorted(groups.items(), key=lambda kv: -kv[1][1]):
        print(f"| {key} | {count / n:.0f} | {t / n:.2f} | {100 * t / total:.0f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
