"""Export benchmark: a trained run's model written as .splat and .spz (and with fewer SH bands), read back, and
rendered from the run's held-out cameras: PSNR of each against the original model's renders and against the
references, file size and size ratio to the PLY.

    python benchmarks/exports.py RUN_DIR            # an mi-gs optimize output folder

Uses ``mi-gs export`` as a user would; renders with the run's settings (``evaluate_views``).
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run")
    args = ap.parse_args(argv)
    run = Path(args.run)

    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from mi_gaussians import run_folder
    from mi_gaussians.runs import run_dataset
    from mi_gaussians.evaluate import display, evaluate_views, summarize
    from mi_gaussians.model.gaussians import Gaussians

    record = run_folder.RunRecord.read(run, "missing")
    cfg = record.train
    ds = run_dataset(record, run)
    views = ds.test or ds.train
    ply = run / run_folder.MODEL
    work = Path(tempfile.mkdtemp())
    mi_gs = str(Path(sys.executable).parent / "mi-gs")
    cases = [("PLY (original)", ply, [])]
    for name, suffix, extra in ((".splat", ".splat", []), (".spz", ".spz", []),
                                (".spz, --sh-degree 1", ".spz", ["--sh-degree", "1"]),
                                (".spz, --sh-degree 0", ".spz", ["--sh-degree", "0"])):
        out = work / f"model_{len(cases)}{suffix}"
        subprocess.run([mi_gs, "export", str(ply), "-o", str(out), *extra], check=True, capture_output=True)
        cases.append((name, out, extra))

    def renders(path):
        scores, _ = evaluate_views(Gaussians.load(path), views, tuple(ds.background), cfg=cfg.raster,
                                   with_lpips=False, keep_images=True, color_space=ds.color_space)
        return scores

    base = renders(ply)
    size0 = ply.stat().st_size
    print(f"\n{run}: {len(views)} held-out views, {Gaussians.load(ply).n:,} Gaussians\n")
    print("| format | bytes per Gaussian | size ratio to the PLY | PSNR vs the PLY's renders | test PSNR |")
    print("|---|---:|---:|---:|---:|")
    n = Gaussians.load(ply).n
    for name, path, _ in cases:
        scores = base if path == ply else renders(path)
        diffs = []
        for a, b in zip(scores, base):
            mse = float(np.mean((display(a.render, ds.color_space).astype(np.float64)
                                 - display(b.render, ds.color_space).astype(np.float64)) ** 2))
            diffs.append(10 * math.log10(1 / mse) if mse > 0 else float("inf"))
        vs = "(itself)" if path == ply else f"{np.mean(diffs):.2f}"
        print(f"| {name} | {path.stat().st_size / n:.1f} | {size0 / path.stat().st_size:.1f} | {vs} | "
              f"{summarize(scores)['psnr']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
