"""How many of a trained model's Gaussians the training views do not need: offline pruning by blending weight.

    python benchmarks/prune_scores.py RUN [--thresholds 9.8e-8 1.25e-6] [--fractions 0.1 0.2]

For the finished run ``RUN`` (its ``point_cloud.ply`` and dataset), every Gaussian's blending weight in every training
view is measured exactly (``mi_gaussians.optim.weights.max_weights``: the sum over the view's pixels of T * alpha,
through the renderer's backward pass, as a share of the view's pixels); its score is the largest over the training
views (the share of the image it gives in the view that sees it most), the statistic ``densify.weight_prune`` prunes
by. The model is then scored on its test views with the Gaussians below each threshold removed (``--thresholds``,
shares of the image; 1/255 of one pixel, the renderer's own cut-off, is 9.8e-8 of a 200x200 image: "no training view
sees it at all") and without the lowest ``--fractions`` of them, with no training afterwards. Prints one table row per case (Markdown).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--thresholds", type=float, nargs="*", default=[9.8e-8, 1.25e-6])
    ap.add_argument("--fractions", type=float, nargs="*", default=[0.1, 0.2])
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args(argv)

    import mitsuba as mi

    mi.set_variant(args.variant)

    from mi_gaussians.config import RasterConfig
    from mi_gaussians.evaluate import evaluate_views, summarize
    from mi_gaussians.model.gaussians import Gaussians
    from mi_gaussians.optim.weights import max_weights
    from mi_gaussians.run_folder import RunRecord
    from mi_gaussians.runs import run_dataset

    rec = RunRecord.read(args.run, "is it an mi-gs optimize output folder?")
    ds = run_dataset(rec, args.run, progress=False, log=None)
    g = Gaussians.load_ply(args.run / "point_cloud.ply")
    t = time.perf_counter()
    score = np.array(max_weights(g, [v.camera for v in ds.train]))
    seconds = time.perf_counter() - t
    p = g.numpy()

    def scored(keep) -> tuple[float, float]:
        g2 = Gaussians.from_numpy(**{k: v[keep] for k, v in p.items()})
        s, _ = evaluate_views(g2, ds.test, ds.background, cfg=RasterConfig(), with_lpips=False,
                              color_space=ds.color_space)
        m = summarize(s)
        return m["psnr"], m["ssim"]

    print(f"{args.run}: {g.n:,} Gaussians, weights over {len(ds.train)} training views in {seconds:.1f} s")
    print("| removed | Gaussians removed | test PSNR | SSIM |\n|---|---:|---:|---:|")
    psnr, ssim = scored(np.ones(g.n, bool))
    print(f"| none | 0 | {psnr:.3f} | {ssim:.4f} |")
    for thr in args.thresholds:
        keep = score >= thr
        psnr, ssim = scored(keep)
        print(f"| max weight over the training views < {thr:.3g} of the image | {int((~keep).sum()):,} "
              f"({(~keep).mean():.1%}) | {psnr:.3f} | {ssim:.4f} |")
    for frac in args.fractions:
        keep = score > np.quantile(score, frac)
        psnr, ssim = scored(keep)
        print(f"| the lowest {frac:.0%} by max weight | {int((~keep).sum()):,} | {psnr:.3f} | {ssim:.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
