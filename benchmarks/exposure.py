"""Exposure compensation at 7k iterations: each dataset trained without it, with ``--exposure`` (affine) and with
``--exposure bilateral``, each scored on the held-out views by the two protocols (``mi-gs eval``): the whole image as
rendered, and the 2024 reference's (a colour transform fitted on the left half of each view, the right half scored).

    python benchmarks/exposure.py fox maryrose mi_objects_colmap --coarser 2

Datasets and options are those of ``benchmarks/strategies.py`` (the README's training table); ``--coarser K`` trains
at K times its -r. Runs go through the command line; a finished run in the output folder (default
/tmp/mi_gs_exposure/<dataset>/<setup>) is reused, an interrupted one resumed.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from cli_run import train  # noqa: E402
from strategies import DATA, DATASETS, ITERATIONS, coarser  # noqa: E402

SETUPS = {"plain": [], "exposure": ["--exposure"], "bilateral": ["--exposure", "bilateral"]}


def evaluate(run: Path) -> dict:
    """``mi-gs eval`` of a run (both protocols), its eval.json."""
    subprocess.run([str(Path(sys.executable).parent / "mi-gs"), "eval", str(run), "--overwrite"], check=True,
                   stdout=subprocess.DEVNULL)
    return json.loads((run / "eval.json").read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("datasets", nargs="+", choices=sorted(DATASETS))
    ap.add_argument("--out", default="/tmp/mi_gs_exposure")
    ap.add_argument("--coarser", type=int, default=1, metavar="K")
    ap.add_argument("--setups", nargs="+", choices=tuple(SETUPS), default=list(SETUPS),
                    help="plain, exposure (--exposure: affine), bilateral (--exposure bilateral); default all")
    args = ap.parse_args(argv)
    rows = []
    for name in args.datasets:
        folder, extra = DATASETS[name]
        extra = coarser(extra, args.coarser)
        src = DATA / folder
        if not src.is_dir():
            print(f"{name}: {src} not found, skipped", file=sys.stderr)
            continue
        res = "-r" + extra[extra.index("-r") + 1] if "-r" in extra else "-r1"
        for setup in args.setups:
            options = SETUPS[setup]
            run = Path(args.out) / res / name / setup
            metrics = train(src, run, ITERATIONS, extra + options)
            e = evaluate(run)
            rows.append((f"{name} {res}", setup, e["mean"], e["half_image"]["mean"], metrics["gaussians"],
                         metrics["training_seconds"] / 60))
    print(f"\n{ITERATIONS} iterations; held-out views scored whole, and by the half-image protocol\n")
    print("| dataset | setup | PSNR | SSIM | half-image PSNR | half-image SSIM | Gaussians | minutes |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name, setup, full, half, n, minutes in rows:
        print(f"| {name} | {setup} | {full['psnr']:.2f} | {full['ssim']:.4f} | {half['psnr']:.2f} | "
              f"{half['ssim']:.4f} | {n:,} | {minutes:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
