"""The blend kernels' lane layouts against each other (``mi_gaussians.raster.blend.LANE_LAYOUTS``): kernel times of
the forward and backward blend loops, the layouts taking turns in one process (a shared VM's speed drifts by tens of
percent between processes and minutes; taking turns gives every layout the same drift).

    python benchmarks/layouts.py 100000:800 10000:256                   # synthetic scenes (benchmarks/render.py's)
    python benchmarks/layouts.py RUN@DATASET                            # a trained run's model on 4 training views
    python benchmarks/layouts.py RUN                                    # the same from the run folder alone
    python benchmarks/layouts.py RUN 100000:800 1000000:1600 --variant cuda_ad_rgb --layouts 4:64 2:128 1:256
    python benchmarks/layouts.py RUN --layouts 8:16 4:16:4 --every-kernel   # tile grids: binning's kernels count too
    python benchmarks/layouts.py RUN --layouts 8:16:8:16 8:8:8:8 --every-kernel --scale 2   # its views at 2x the size

``RUN`` is a run folder (its ``point_cloud.ply``), ``DATASET`` the dataset folder it was trained on (read at full
resolution, white background). A run folder alone takes 4 of the training cameras its ``cameras.json`` lists and the
background its ``config.json`` records (what a GPU machine needs to be sent: the folder's two files and the model).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np

NAMES = ("means", "scales", "rotations", "opacities", "sh_dc", "sh_rest")


def scaled(cam, s: int):
    """``cam`` rendering ``s`` times as many pixels along each side (the same view: ``Camera.scaled``)."""
    return cam.scaled(cam.width * s, cam.height * s)


def cases(specs, scale: int = 1):
    import mi_gaussians as mig
    from mi_gaussians.data.dataset import load_dataset
    from mi_gaussians.run_folder import CAMERAS, MODEL, RunRecord
    from render import make_scene

    for spec in specs:
        if "@" in spec:
            run, data = spec.split("@", 1)
            g = mig.Gaussians.load_ply(Path(run) / "point_cloud.ply")
            ds = load_dataset(data, resolution=1, background=(1, 1, 1))
            views = ds.train[::max(1, len(ds.train) // 4)][:4]
            cams = [scaled(v.camera, scale) for v in views]
            yield f"{Path(run).name} ({g.n:,} Gaussians, {cams[0].width}x{cams[0].height})", g, cams, (1.0, 1.0, 1.0)
        elif ":" not in spec:
            run = Path(spec)
            g = mig.Gaussians.load_ply(run / MODEL)
            train = json.loads((run / CAMERAS).read_text())["train"]
            cams = [scaled(mig.Camera.from_dict(c, str(run / CAMERAS)), scale)
                    for c in train[::max(1, len(train) // 4)][:4]]
            bg = tuple(RunRecord.read(run, "a run folder holds its config.json").train.data.background)
            yield f"{run.name} ({g.n:,} Gaussians, {cams[0].width}x{cams[0].height})", g, cams, bg
        else:
            n, res = map(int, spec.split(":"))
            cam = mig.Camera(res, res, res / 1.2, res / 1.2, res / 2, res / 2, np.eye(4))
            yield f"synthetic {n:,} Gaussians, {res}x{res}", mig.Gaussians.from_numpy(**make_scene(n)), [cam], \
                (0.0, 0.0, 0.0)


def blend_ms(g, cams, background, every_kernel: bool = False) -> tuple[float, float]:
    """Mean over the cameras of the longest kernel of the forward render and of the backward pass (the blend loops);
    with ``every_kernel`` the sum of all their kernels (projection and binning too: a tile grid changes those)."""
    import drjit as dr
    import mi_gaussians as mig

    f = b = 0.0
    for cam in cams:
        for k in NAMES:
            dr.enable_grad(getattr(g, k))
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            out = mig.render(g, cam, background=background)
            dr.eval(out.rgb)
            dr.sync_thread()
            forward = dr.kernel_history()
            dr.backward(dr.sum(out.rgb.array * out.rgb.array))
            dr.eval([dr.grad(getattr(g, k)) for k in NAMES])
            dr.sync_thread()
            backward = dr.kernel_history()
        for k in NAMES:
            dr.disable_grad(getattr(g, k))
        pick = sum if every_kernel else max
        f += pick(k.get("execution_time", 0.0) for k in forward)
        b += pick(k.get("execution_time", 0.0) for k in backward)
    return f / len(cams), b / len(cams)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", nargs="+", metavar="N:RES | RUN@DATASET | RUN")
    ap.add_argument("--repeats", type=int, default=5, help="timed turns per layout (after one untimed turn)")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--layouts", nargs="+", default=["4:64", "8:16", "16:16"],
                    metavar="PIXELS:START_LANES[:TILE_ROWS[:TILE_COLS]]",
                    help="lane layouts (tile rows and columns: 16 unless given)")
    ap.add_argument("--scale", type=int, default=1, help="render a run's views at this many times their size")
    ap.add_argument("--every-kernel", action="store_true",
                    help="time every kernel of the render and its backward pass, not only the blend loops")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import mitsuba as mi

    mi.set_variant(args.variant)
    import drjit as dr

    from mi_gaussians.raster import blend

    layouts = {s: blend.LaneLayout(*map(int, s.split(":"))) for s in args.layouts}
    print(f"variant {args.variant}, {dr.thread_count()} threads; the active backend's default: "
          f"{blend.lane_layout()}")
    print("| case | pixels per lane : start lanes [: tile rows [: tile columns]] | forward ms (median / best) "
          "| backward ms (median / best) | fwd+bwd median |\n|---|---|---:|---:|---:|")
    default = blend.lane_layout
    try:
        for label, g, cams, bg in cases(args.cases, args.scale):
            times = {s: ([], []) for s in layouts}
            for turn in range(args.repeats + 1):
                for s, layout in layouts.items():
                    blend.lane_layout = lambda layout=layout: layout      # (read by make_frame at each render)
                    f, b = blend_ms(g, cams, bg, args.every_kernel)
                    if turn:
                        times[s][0].append(f)
                        times[s][1].append(b)
            for s, (f, b) in times.items():
                both = statistics.median([x + y for x, y in zip(f, b)])
                print(f"| {label} | {s} | {statistics.median(f):.1f} / {min(f):.1f} | {statistics.median(b):.1f} / "
                      f"{min(b):.1f} | {both:.1f} |", flush=True)
    finally:
        blend.lane_layout = default
    return 0


if __name__ == "__main__":
    sys.exit(main())
