"""Camera pose optimisation measured: runs with known pose errors (``data.pose_noise``), with and without
``--pose-opt``, through the command line; held-out PSNR / SSIM and the training cameras' errors before and after.

    python benchmarks/pose.py mi_objects_colmap_r2 --noise 1 0.01            # exact, noisy, noisy + --pose-opt
    python benchmarks/pose.py mi_objects_colmap_r2 --noise 1 0.01 --lr 1e-5 1e-4 3e-4 1e-3:0.01   # LR[:DECAY]
    python benchmarks/pose.py mi_objects_colmap_r2 --noise 1 0 --pivot centre depth  # where the turn pivots
    python benchmarks/pose.py fox --noise 0 0                                 # a real capture: with and without

Runs are kept in --out (default /tmp/mi_gs_pose/<dataset>/<setup>) and reused; an interrupted one resumes. The
errors are against the dataset's own cameras (on a real capture, how far --pose-opt moved them).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from ablation import DATA, DATASETS as ABLATION_DATASETS  # noqa: E402
from cli_run import train  # noqa: E402

DATASETS = {**ABLATION_DATASETS, "mi_room_colmap_r2": ("mi_room/colmap", ["-r", "2"])}


def setups(noise: tuple[float, float], lrs: list[str | None], pivots: list[str] | None = None) -> dict[str, list[str]]:
    """setup name -> options: the exact cameras (when there is noise), the noisy ones, and --pose-opt at each rate
    (``LR`` or ``LR:DECAY``, optim.pose_opt_lr and optim.pose_opt_lr_decay; None: the default) and each pivot
    (optim.pose_opt_pivot; None: the default; a setup's name says "_pivot_depth" where the pivot is "depth")."""
    deg, frac = noise
    noisy = ["--set", f"data.pose_noise={deg:g},{frac:g}"] if deg or frac else []
    out = {"exact": []} if noisy else {}
    out[f"noise_{deg:g}_{frac:g}" if noisy else "given"] = noisy
    for lr in lrs:
        for pivot in pivots or [None]:
            name = ("noise" if noisy else "given") + \
                f"{'_' + format(deg, 'g') + '_' + format(frac, 'g') if noisy else ''}"
            rate, _, decay = (lr or "").partition(":")
            name += "_pose_opt" + (f"_lr{float(rate):g}" if rate else "") + \
                (f"_decay{float(decay):g}" if decay else "") + ("_pivot_depth" if pivot == "depth" else "")
            out[name] = noisy + ["--pose-opt"] + (["--set", f"optim.pose_opt_lr={float(rate):g}"] if rate else []) + \
                (["--set", f"optim.pose_opt_lr_decay={float(decay):g}"] if decay else []) + \
                (["--set", f"optim.pose_opt_pivot={pivot}"] if pivot else [])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+", choices=sorted(DATASETS))
    ap.add_argument("--noise", type=float, nargs=2, default=(1.0, 0.01), metavar=("DEGREES", "FRACTION"))
    ap.add_argument("--lr", nargs="*", default=None, metavar="LR[:DECAY]",
                    help="pose learning rates, each with its decay factor (default: the default)")
    ap.add_argument("--pivot", nargs="*", default=None, choices=["centre", "depth"],
                    help="where the corrections turn the cameras (optim.pose_opt_pivot; default: the default)")
    ap.add_argument("--only", nargs="*", default=None, help="run only these setups")
    ap.add_argument("--iterations", type=int, default=7000)
    ap.add_argument("--out", type=Path, default=Path("/tmp/mi_gs_pose"))
    args = ap.parse_args(argv)
    for lr in args.lr or []:
        try:
            [float(x) for x in lr.split(":", 1)]
        except ValueError:
            ap.error(f"--lr {lr}: expected LR or LR:DECAY (numbers)")
    rows = []
    for name in args.datasets:
        folder, extra = DATASETS[name]
        src = DATA / folder
        if not src.is_dir():
            print(f"{name}: {src} not found, skipped", file=sys.stderr)
            continue
        for setup, options in setups(tuple(args.noise), args.lr or [None], args.pivot).items():
            if args.only and setup not in args.only:
                continue
            out = args.out / name / f"{setup}_{args.iterations}"
            m = train(src, out, args.iterations, [*extra, *options])
            rows.append((name, setup, m))
            print(json.dumps({"dataset": name, "setup": setup, "psnr": m["mean"]["psnr"],
                              "poses": m.get("poses")}), file=sys.stderr, flush=True)
    print(f"\n{args.iterations} iterations; errors of the training cameras against the dataset's, start -> end\n")
    print("| dataset | setup | PSNR | SSIM | rotation error (deg) | translation error (of the extent) | "
          "reprojection error (px) | Gaussians | minutes |")
    print("|---|---|---:|---:|---|---|---|---:|---:|")
    for name, setup, m in rows:
        p = m.get("poses")
        rot = "-" if p is None else "{start:.3f} -> {end:.3f}".format(**p["rotation_error_degrees"])
        tr = "-" if p is None else "{start:.4f} -> {end:.4f}".format(**p["translation_error_of_extent"])
        px = "-" if p is None or "reprojection_error_pixels" not in p else \
            "{start:.2f} -> {end:.2f}".format(**p["reprojection_error_pixels"])
        print(f"| {name} | {setup} | {m['mean']['psnr']:.2f} | {m['mean']['ssim']:.4f} | {rot} | {tr} | {px} | "
              f"{m['gaussians']:,} | {m['training_seconds'] / 60:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
