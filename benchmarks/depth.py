"""Depth supervision benchmark: Mitsuba scenes trained with and without ``--depth-weight 1`` (in the same run, same
seed, references shared): PSNR / SSIM on the held-out views and the mean absolute error of the rendered expected
depth against Mitsuba's exact depth there (scene units, over the pixels both cover; ``coverage``: the share of the
reference's surface pixels the model covers).

    python benchmarks/depth.py                         # scenes/room.xml and scenes/objects.xml, 3k iterations
    python benchmarks/depth.py --scenes room --iterations 7000

Each model is trained with the command line (``mi-gs optimize``); a finished run in the output folder (default
/tmp/mi_gs_depth/<scene>/<setup>) is reused, an interrupted one resumed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from cli_run import train  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["room", "objects"])
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--weight", default="1")
    ap.add_argument("--out", default="/tmp/mi_gs_depth")
    args = ap.parse_args(argv)
    rows = []
    for name in args.scenes:
        scene = ROOT / "scenes" / f"{name}.xml"
        root = Path(args.out) / name
        for label, extra in (("default", []), (f"--depth-weight {args.weight}", ["--depth-weight", args.weight])):
            m = train(scene, root / ("depth" if extra else "default"), args.iterations,
                      ["--cache", str(root / "references"), *extra])
            rows.append((name, label, m["mean"]["psnr"], m["mean"]["ssim"], m.get("depth_mae"),
                         m.get("depth_coverage"), m["gaussians"], m["training_seconds"] / 60))
    print(f"\n{args.iterations} iterations; held-out views\n")
    print("| scene | loss | PSNR | SSIM | depth MAE | coverage | Gaussians | minutes |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name, label, psnr, ssim, mae, cov, n, minutes in rows:
        print(f"| scenes/{name}.xml | {label} | {psnr:.2f} | {ssim:.4f} | {mae:.4f} | {cov:.4f} | {n:,} | "
              f"{minutes:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
