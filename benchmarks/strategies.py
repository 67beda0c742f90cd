"""Densification strategies at 7k iterations, in one run per dataset: the paper's default, ``--absgrad``, and
``--strategy mcmc`` capped at the default's final count and at half of it (the cap is read from the default run of
this benchmark). Prints PSNR / SSIM on the held-out views, the final count and the training minutes.

    python benchmarks/strategies.py mi_objects_colmap             # ../shared/data/mi_objects/colmap, 200x200
    python benchmarks/strategies.py fox maryrose                   # the real captures (about 1 h per run each)
    python benchmarks/strategies.py mi_objects_colmap --only default mcmc_full
    python benchmarks/strategies.py fox maryrose --coarser 2          # at twice the README's -r (about 4x cheaper)

Each model is trained with the command line (``mi-gs optimize``), as a user would; a finished run in the output
folder (default /tmp/mi_gs_strategies/<dataset>/<setup>) is reused, an interrupted one resumed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from cli_run import train  # noqa: E402
DATA = (ROOT / ".." / "shared" / "data").resolve()
ITERATIONS = 7000

# dataset -> (folder under ../shared/data, optimize options) as the README's training table runs them
DATASETS = {
    "mi_objects_colmap": ("mi_objects/colmap", ["--white-background"]),
    "fox": ("fox", ["-r", "4"]),
    "maryrose": ("maryrose", ["-r", "8", "--white-background"]),
}
SETUPS = ("default", "absgrad", "mcmc_full", "mcmc_half")


def coarser(options: list[str], factor: int) -> list[str]:
    """``options`` with its ``-r`` multiplied by ``factor`` (``-r factor`` where it has none)."""
    if factor == 1:
        return list(options)
    if "-r" not in options:
        return [*options, "-r", str(factor)]
    i = options.index("-r")
    return [*options[:i + 1], str(int(options[i + 1]) * factor), *options[i + 2:]]


def run_dataset(name: str, out_root: Path, only: set[str], factor: int = 1) -> list[tuple]:
    folder, extra = DATASETS[name]
    extra = coarser(extra, factor)
    src = DATA / folder
    if not src.is_dir():
        print(f"{name}: {src} not found, skipped", file=sys.stderr)
        return []
    rows = []
    res = "-r" + extra[extra.index("-r") + 1] if "-r" in extra else "-r1"
    out_root = out_root if factor == 1 else out_root / res
    default = train(src, out_root / name / "default", ITERATIONS, extra)
    cap = int(default["gaussians"])
    options = {"default": [], "absgrad": ["--absgrad"],
               "mcmc_full": ["--strategy", "mcmc", "--max-gaussians", str(cap)],
               "mcmc_half": ["--strategy", "mcmc", "--max-gaussians", str(cap // 2)]}
    for setup in SETUPS:
        if setup not in only:
            continue
        m = default if setup == "default" else train(src, out_root / name / setup, ITERATIONS, extra + options[setup])
        rows.append((name if factor == 1 else f"{name} {res}", setup, " ".join(options[setup]) or "(default)", m["mean"]["psnr"], m["mean"]["ssim"],
                     m["gaussians"], m["training_seconds"] / 60))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("datasets", nargs="+", choices=sorted(DATASETS))
    ap.add_argument("--only", nargs="+", choices=SETUPS, default=list(SETUPS))
    ap.add_argument("--out", default="/tmp/mi_gs_strategies")
    ap.add_argument("--coarser", type=int, default=1, metavar="K",
                    help="train at K times the README's -r, every setup alike (a cheaper comparison)")
    args = ap.parse_args(argv)
    if args.coarser < 1:
        ap.error("--coarser: must be 1 or more")
    rows = []
    for name in args.datasets:
        rows += run_dataset(name, Path(args.out), set(args.only), args.coarser)
    print(f"\n{ITERATIONS} iterations; PSNR / SSIM on the held-out views\n")
    print("| dataset | strategy | options | PSNR | SSIM | Gaussians | minutes |")
    print("|---|---|---|---:|---:|---:|---:|")
    for name, setup, opts, psnr, ssim, n, minutes in rows:
        print(f"| {name} | {setup} | `{opts}` | {psnr:.2f} | {ssim:.4f} | {n:,} | {minutes:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
