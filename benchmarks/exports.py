"""Export benchmark: a model written in each web format (.glb, .gltf, .spz version 4 and 3, with fewer SH bands,
.splat), read back and rendered: bytes per Gaussian, size ratio to the PLY, PSNR of each against the PLY's own renders
(and, for a run, test PSNR against the references).

    python benchmarks/exports.py RUN_DIR                              # an mi-gs optimize output folder: its held-out
                                                                      # views, its render settings
    python benchmarks/exports.py --model M.ply --camera CAM.json      # a lone model: CAM.json and copies of it turned
                                          [--views 12]                # about the model's centre (the camera's up axis)

Uses ``mi-gs export`` as a user would; prints a Markdown table.
"""

from __future__ import annotations

import argparse
import math
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CASES = ((".glb", ".glb", []), (".gltf", ".gltf", []), (".spz (version 4)", ".spz", []),
         (".spz --spz-version 3", ".spz", ["--spz-version", "3"]),
         (".spz --sh-degree 1", ".spz", ["--sh-degree", "1"]), (".spz --sh-degree 0", ".spz", ["--sh-degree", "0"]),
         (".splat", ".splat", []))


def orbit(cam, centre: np.ndarray, n: int) -> list:
    """``cam`` and ``n - 1`` copies turned about the axis through ``centre`` along the camera's up direction."""
    import dataclasses

    c2w = np.linalg.inv(cam.world_to_camera)
    up = -c2w[:3, 1]                                          # (OpenCV: y is down)
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        kx = np.array([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
        rot = np.eye(3) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rot, centre - rot @ centre
        out.append(dataclasses.replace(cam, world_to_camera=np.linalg.inv(m @ c2w), name=f"orbit_{k:02d}"))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", nargs="?", help="an mi-gs optimize output folder")
    ap.add_argument("--model", help="a lone model (.ply), with --camera")
    ap.add_argument("--camera", help="camera JSON for --model")
    ap.add_argument("--views", type=int, default=12, help="cameras around a lone model (default 12)")
    args = ap.parse_args(argv)
    if (args.run is None) == (args.model is None) or (args.model is not None and args.camera is None):
        ap.error("give RUN_DIR, or --model M.ply --camera CAM.json")

    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from mi_gaussians import run_folder
    from mi_gaussians.config import RasterConfig
    from mi_gaussians.data.camera import Camera
    from mi_gaussians.evaluate import display, evaluate_views, summarize
    from mi_gaussians.model.gaussians import Gaussians
    from mi_gaussians.raster.rasterize import render
    from mi_gaussians.runs import run_dataset

    if args.run is not None:
        run = Path(args.run)
        record = run_folder.RunRecord.read(run, "missing")
        ds = run_dataset(record, run)
        views, ply, raster, space = ds.test or ds.train, run / run_folder.MODEL, record.train.raster, ds.color_space
        background = tuple(ds.background)
    else:
        ply, raster, space, background = Path(args.model), RasterConfig(), "srgb", (0.0, 0.0, 0.0)
        g = Gaussians.load(ply)
        views = orbit(Camera.from_json(args.camera), np.asarray(g.numpy()["means"], np.float64).mean(0), args.views)
    work = Path(tempfile.mkdtemp())
    mi_gs = str(Path(sys.executable).parent / "mi-gs")
    cases = [("PLY", ply)]
    for name, suffix, extra in CASES:
        out = work / f"model_{len(cases)}{suffix}"
        subprocess.run([mi_gs, "export", str(ply), "-o", str(out), *extra], check=True, capture_output=True)
        cases.append((name, out))

    def images(path):
        g = Gaussians.load(path)
        if args.run is not None:
            scores, _ = evaluate_views(g, views, background, cfg=raster, with_lpips=False, keep_images=True,
                                       color_space=space)
            return [s.render for s in scores], summarize(scores)["psnr"]
        return [np.array(render(g, v, background=background, cfg=raster).rgb) for v in views], None

    base, _ = images(ply)
    n, size0 = Gaussians.load(ply).n, ply.stat().st_size
    what = f"{len(views)} held-out views" if args.run else f"{len(views)} cameras around it"
    print(f"\n{args.run or args.model}: {n:,} Gaussians of SH degree {Gaussians.load(ply).sh_degree}, {what}; "
          f"{platform.node()}, {platform.processor() or platform.machine()}\n")
    print("| format | bytes per Gaussian | size ratio to the PLY | PSNR against the PLY's renders |"
          + (" test PSNR |" if args.run else ""))
    print("|---|---:|---:|---:|" + ("---:|" if args.run else ""))
    for name, path in cases:
        imgs, test = images(path)
        diffs = []
        for a, b in zip(imgs, base):
            mse = float(np.mean((display(a, space).astype(np.float64) - display(b, space).astype(np.float64)) ** 2))
            diffs.append(10 * math.log10(1 / mse) if mse > 0 else float("inf"))
        vs = "(itself)" if path == ply else ("lossless" if min(diffs) == float("inf") else f"{np.mean(diffs):.2f}")
        print(f"| {name} | {path.stat().st_size / n:.1f} | {size0 / path.stat().st_size:.1f} | {vs} |"
              + (f" {test:.2f} |" if args.run else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
