"""Mitsuba example scenes: held-out PSNR / SSIM / Gaussians / minutes per initialization method.

    python benchmarks/scenes.py objects --init shapes random sfm --iterations 3000
    python benchmarks/scenes.py room --iterations 3000

Runs what ``mi-gs optimize scenes/<name>.xml --iterations N --init M`` runs (references rendered once and shared
between the runs through --out/<scene>/references), and prints one table row per (scene, init): seconds spent making
the initial points, their number, then test PSNR / SSIM, Gaussians and training minutes at the end.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_one(scene: str, init: str, iterations: int, out_root: Path, init_points: int | None = None) -> dict:
    from mi_gaussians.config import SceneConfig, TrainConfig
    from mi_gaussians.data.scene_dataset import load_scene_dataset
    from mi_gaussians.optim.trainer import Trainer

    path = ROOT / "scenes" / f"{scene}.xml"
    scfg = dataclasses.replace(SceneConfig(), init=init, init_points=init_points or SceneConfig().init_points)
    cfg = dataclasses.replace(TrainConfig(scene=scfg, checkpoint_every=iterations, eval_every=max(500, iterations // 6),
                                          save_iterations=()).with_iterations(iterations))
    refs = out_root / scene / "references"
    # render (or reuse) the references first, so that the init timing below is the init alone
    load_scene_dataset(path, dataclasses.replace(scfg, init="random", init_points=1), cache_root=refs,
                          log=lambda s: print(s, file=sys.stderr))
    t0 = time.perf_counter()
    ds = load_scene_dataset(path, scfg, cache_root=refs, progress=False, log=lambda s: print(s, file=sys.stderr))
    init_s = time.perf_counter() - t0
    out = out_root / scene / (init if init_points is None else f"{init}_{init_points}")
    tr = Trainer(ds, cfg, out, progress=True)
    m = tr.run(resume=(out / "checkpoints" / "ckpt.npz").exists())
    return {"scene": scene, "init": init, "init_s": init_s, "points": len(ds.points_xyz), "psnr": m["mean"]["psnr"],
            "ssim": m["mean"]["ssim"], "gaussians": m["gaussians"], "minutes": m["training_seconds"] / 60.0,
            "views": f"{len(ds.train)}+{len(ds.test)}", "size": f"{ds.train[0].camera.width}x{ds.train[0].camera.height}"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", help="names of scenes/<name>.xml")
    ap.add_argument("--init", nargs="+", default=["shapes"], choices=("shapes", "random", "sfm"))
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--init-points", type=int, nargs="+", default=[None],
                    help="initial points for shapes/random (default: SceneConfig's); several values: one run each")
    ap.add_argument("--out", default="/tmp/mi_gs_scenes")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args(argv)
    import mitsuba as mi

    mi.set_variant(args.variant)
    import mi_gaussians  # noqa: F401  (registers the plugins)

    rows = [run_one(s, i, args.iterations, Path(args.out), n) for s in args.scenes for i in args.init
            for n in (args.init_points if i != "sfm" else [None])]
    print(f"\n{args.iterations} iterations each\n")
    print("| scene | views (train+test) | init | init seconds | initial points | test PSNR | test SSIM | Gaussians "
          "| training minutes |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['scene']} | {r['views']} at {r['size']} | {r['init']} | {r['init_s']:.1f} | {r['points']:,} "
              f"| {r['psnr']:.2f} | {r['ssim']:.4f} | {r['gaussians']:,} | {r['minutes']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
