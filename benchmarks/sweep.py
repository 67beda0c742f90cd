"""The cost of Ray per run: the same runs trained one after another with ``mi-gs optimize`` and as one
``mi-gs sweep`` (one run at a time, with every CPU, so that only the way they are started differs).

    python benchmarks/sweep.py [--iterations 500] [--out /tmp/mi_gs_sweep_overhead]

Runs: mi_objects/colmap and mi_objects/blender (../shared/data) at -r 4, default and MCMC, seeds 0 and 1. Prints a
table: wall seconds per run, training seconds per run, and what is neither (starting the process or the Ray
worker, loading the dataset, evaluating, writing the outputs).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MI_GS = str(Path(sys.executable).parent / "mi-gs")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--iterations", type=int, default=500)
    ap.add_argument("--out", default="/tmp/mi_gs_sweep_overhead")
    args = ap.parse_args()
    datasets = [DATA / "mi_objects" / "colmap", DATA / "mi_objects" / "blender"]
    if not all(d.is_dir() for d in datasets):
        print(f"{DATA}: the shared datasets are missing", file=sys.stderr)
        return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cpus = os.cpu_count() or 1
    spec = out / "spec.toml"
    spec.write_text(f"datasets = {json.dumps([str(d) for d in datasets])}\niterations = {args.iterations}\n"
                    f"seeds = [0, 1]\n[set]\n\"data.resolution\" = 4\neval_every = 0\n[grid]\n"
                    f"strategy = [\"default\", \"mcmc\"]\n[resources]\ncpus = {cpus}\n")
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from mi_gaussians.cluster.sweep_spec import read_spec

    runs = read_spec(spec).runs
    # one after another, as a shell loop would
    seq_train, t0 = 0.0, time.perf_counter()
    for r in runs:
        folder = out / "sequential" / r.name
        subprocess.run([MI_GS, "optimize", str(r.dataset), "-o", str(folder), "--overwrite", "--quiet",
                        "--iterations", str(args.iterations), "--eval-every", "0", "-r", "4", "--seed", str(r.seed),
                        "--strategy", dict(r.setting)["strategy"]], check=True, stdout=subprocess.DEVNULL)
        seq_train += json.loads((folder / "metrics.json").read_text())["training_seconds"]
    seq_wall = time.perf_counter() - t0
    # one sweep (its own local Ray cluster, started and stopped by the command)
    t0 = time.perf_counter()
    subprocess.run([MI_GS, "sweep", str(spec), "-o", str(out / "sweep"), "--overwrite", "--quiet"], check=True,
                   stdout=subprocess.DEVNULL)
    sweep_wall = time.perf_counter() - t0
    sweep_train = sum(json.loads((out / "sweep" / "runs" / r.name / "metrics.json").read_text())["training_seconds"]
                      for r in runs)
    n = len(runs)
    print(f"\n{n} runs of {args.iterations} iterations (mi_objects colmap + blender at -r 4, default + MCMC, "
          f"2 seeds), one at a time on {cpus} CPUs\n")
    print("| how | wall s per run | training s per run | the rest per run |")
    print("|---|---:|---:|---:|")
    for name, wall, train in (("mi-gs optimize, one after another", seq_wall, seq_train),
                              ("mi-gs sweep (Ray)", sweep_wall, sweep_train)):
        print(f"| {name} | {wall / n:.2f} | {train / n:.2f} | {(wall - train) / n:.2f} |")
    print(f"\nRay's cost per run: {(sweep_wall - seq_wall) / n:+.2f} s of wall time "
          f"({(sweep_wall - sweep_train - seq_wall + seq_train) / n:+.2f} s outside training)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
