"""The work of a training step: Gaussian-tile pairs (instances) per pixel and Gaussians per tile, as a run grows and
for its final model, with each footprint rule, and where a step's time goes.

    python benchmarks/work.py RUN [RUN ...]                 # finished run folders (mi-gs optimize -o RUN)
    python benchmarks/work.py RUN --views 4 --repeats 5     # time forward + backward on 4 test views

Per run: from its history.json (iterations recorded since the footprint change), the blended instances per pixel
at 1k steps along the run beside the Gaussians; for its final model on its test views (``--views`` of them), the
instances of each footprint rule ('box': every tile of the alpha >= 1/255 ellipse's bounding box, 'ellipse': the
tiles it reaches), per pixel and per tile, and the forward + backward wall time of a render with each rule (median
of ``--repeats``, the rules taking turns, compilation excluded) with its share of blend kernels (``dr.kernel_history``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def along_the_run(run: Path, pixels: float, every: int = 1000) -> list[tuple[int, int, float]]:
    """(iteration, Gaussians, mean blended instances per pixel over the ``every`` iterations before it); ``pixels``:
    of a training view (the mean)."""
    h = json.loads((run / "history.json").read_text())
    inst = h.get("instances") or []
    if len(inst) != len(h["iteration"]):
        return []
    rows = []
    for end in range(every, h["iteration"][-1] + 1, every):
        sel = [i for i, it in enumerate(h["iteration"]) if end - every < it <= end]
        if sel:
            rows.append((end, h["gaussians"][sel[-1]], statistics.mean(inst[i] for i in sel) / pixels))
    return rows


def final_model(run: Path, n_views: int, repeats: int) -> dict:
    import drjit as dr
    import mitsuba as mi

    from mi_gaussians.model.gaussians import Gaussians
    from mi_gaussians.raster.blend import lane_layout
    from mi_gaussians.raster.rasterize import render
    from mi_gaussians.run_folder import RunRecord
    from mi_gaussians.runs import model_raster_config, run_dataset

    record = RunRecord.read(run, "is it an mi-gs optimize output folder?")
    ds = run_dataset(record, run, progress=False, log=None)
    views = (ds.test or ds.train)[:n_views]
    g = Gaussians.load_ply(run / "point_cloud.ply")
    base = model_raster_config(run / "point_cloud.ply")
    cfgs = {rule: dataclasses.replace(base, footprint=rule) for rule in ("box", "ellipse")}
    bg = tuple(float(b) for b in ds.background)

    def step(view, cfg):
        params = [g.means, g.scales, g.rotations, g.opacities, g.sh_dc, g.sh_rest]
        for p in params:
            dr.enable_grad(p)
        out = render(g, view.camera, background=bg, cfg=cfg)
        dr.backward(dr.mean(out.rgb.array))
        dr.eval(*(dr.grad(p) for p in params))
        for p in params:
            dr.disable_grad(p)
            dr.clear_grad(p)
        return out

    res = {rule: {"instances": 0, "blended": 0, "seconds": [], "blend_share": []} for rule in cfgs}
    pixels = tiles = 0
    for v in views:
        pixels += v.camera.width * v.camera.height
        tiles_x, tiles_y = lane_layout().tiles(v.camera.width, v.camera.height)
        tiles += tiles_x * tiles_y
        lanes = tiles_x * tiles_y * lane_layout().lanes_per_tile
        for rule, cfg in cfgs.items():
            out = step(v, cfg)
            res[rule]["instances"] += int(out.n_instances)
            res[rule]["blended"] += int(out.n_blended[0])
            step(v, cfg)                    # (compiled)
        for _ in range(repeats):
            for rule, cfg in cfgs.items():
                dr.kernel_history_clear()
                with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
                    dr.sync_thread()
                    t0 = time.perf_counter()
                    step(v, cfg)
                    dr.sync_thread()
                    res[rule]["seconds"].append(time.perf_counter() - t0)
                    hist = dr.kernel_history()
                total = sum(h.get("execution_time", 0.0) for h in hist) or 1.0
                blend = sum(h.get("execution_time", 0.0) for h in hist
                            if str(h["type"]).endswith("JIT") and h.get("size") == lanes)
                res[rule]["blend_share"].append(blend / total)
    train_pixels = statistics.mean(v.camera.width * v.camera.height for v in ds.train)
    return {"views": len(views), "gaussians": g.n, "pixels": pixels, "tiles": tiles, "rules": res,
            "train_pixels": train_pixels}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args(argv)
    import mitsuba as mi

    mi.set_variant(args.variant)
    import drjit as dr

    print(f"variant {args.variant}, {dr.thread_count()} threads\n")
    print("| run | Gaussians | views | footprint | instances per pixel | Gaussians per tile | blended of the box's "
          "| forward + backward ms | blend kernels' share |")
    print("|---|---:|---:|---|---:|---:|---:|---:|---:|")
    curves = []
    for run in args.runs:
        r = final_model(run, args.views, args.repeats)
        box = r["rules"]["box"]["blended"]
        for rule, v in r["rules"].items():
            ms = 1000 * statistics.median(v["seconds"]) if v["seconds"] else float("nan")
            share = statistics.mean(v["blend_share"]) if v["blend_share"] else float("nan")
            print(f"| {run.name} | {r['gaussians']:,} | {r['views']} | {rule} | {v['blended'] / r['pixels']:.1f} "
                  f"| {v['blended'] / r['tiles']:.0f} | {v['blended'] / max(box, 1):.2f} | {ms:.1f} | "
                  f"{100 * share:.0f} % |", flush=True)
        curves.append((run, along_the_run(run, r["train_pixels"])))
    for run, rows in curves:
        if rows:
            print(f"\n{run.name}: along the run (blended instances per pixel, mean over each 1k iterations)\n")
            print("| iteration | Gaussians | instances per pixel |\n|---:|---:|---:|")
            for it, n, per_pixel in rows:
                print(f"| {it:,} | {n:,} | {per_pixel:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
