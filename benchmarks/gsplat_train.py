"""gsplat's ``examples/simple_trainer.py`` recipe (gsplat 1.5.3, its defaults) on one of ``benchmarks/train.py``'s
datasets, scored exactly as ours are: the training comparison of the GPU benchmarks.

    python benchmarks/gsplat_train.py mi_objects_colmap --milestones 7000 --schedule 30000
    python benchmarks/train.py mi_objects_colmap --milestones 7000 --schedule 30000 --variant cuda_ad_rgb  # ours

Needs PyTorch, gsplat and a CUDA device (``gsplat_peer.available()``). The recipe, as ``simple_trainer.py`` has it:
the initial points, scales from the mean squared distance to the 3 nearest neighbours, random quaternions
(``torch.rand``), opacity 0.1, degree-3 SH (one more degree every 1000 steps); Adam (eps 1e-15) with lrs means
1.6e-4 x scene scale (decayed to 1 % over the schedule), scales 5e-3, quats 1e-3, opacities 5e-2, SH DC 2.5e-3, SH rest
2.5e-3 / 20; loss 0.8 L1 + 0.2 (1 - SSIM) (SSIM over the valid region, as ``fused_ssim(padding="valid")``);
``DefaultStrategy`` with its defaults (refine from 500 to 15k every 100 steps, opacity reset every 3000); one image per
step, shuffled each epoch; ``packed=False``; near plane 0.01. Differences, so that both fit the same data: the dataset
is loaded by our loader (same images, cameras, train/test split, and the initial points ``mi-gs optimize`` starts
from: the layout's SfM points, else triangulated from the posed images) without gsplat's world normalization
(the lengths it uses are relative to the scene scale, its ``scene_scale * 1.1``: ``Dataset.extent``, the cameras'
spread, which ``mi-gs optimize`` uses only under ``--set data.extent=cameras``; except the
near plane, 0.01 here in the dataset's units, in its normalized world there), and it renders over the dataset's
background (white for mi_objects/colmap, as our run) where simple_trainer has none.

Scores: the test views rendered by gsplat, compared by our metrics (:mod:`mi_gaussians.metrics`, through
``evaluate.display``, as ``mi-gs`` scores its own) and, as a cross-check, the same model exported to our layout and
rendered by our rasterizer (``evaluate_views``). Minutes are training time without the evaluations.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def knn_mean_sq_dist(points, k: int = 3, chunk: int = 4096):
    """Mean squared distance of each point to its ``k`` nearest other points (simple_trainer's ``knn(points, 4)``)."""
    import torch

    out = []
    for i in range(0, len(points), chunk):
        d2 = torch.cdist(points[i:i + chunk], points).square()
        out.append(d2.topk(k + 1, dim=1, largest=False).values[:, 1:].mean(dim=1))
    return torch.cat(out)


def ssim_valid(img, ref):
    """SSIM of (1, 3, H, W) images, 11 x 11 Gaussian window (sigma 1.5), over the valid region (no padding)."""
    import torch
    import torch.nn.functional as F

    x = torch.arange(11, dtype=torch.float32, device=img.device) - 5.0
    g = torch.exp(-x.square() / (2 * 1.5 ** 2))
    g = g / g.sum()
    w = (g[:, None] * g[None, :]).expand(3, 1, 11, 11).contiguous()

    def blur(v):
        return F.conv2d(v, w, groups=3)

    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu1, mu2 = blur(img), blur(ref)
    s11, s22, s12 = blur(img * img) - mu1 ** 2, blur(ref * ref) - mu2 ** 2, blur(img * ref) - mu1 * mu2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s11 + s22 + c2))
    return m.mean()


def init_splats(ds, scene_scale: float, device: str = "cuda"):
    """simple_trainer's ``create_splats_with_optimizers`` for ``init_type="sfm"``, SH degree 3."""
    import torch

    from mi_gaussians.conventions import rgb_to_sh_dc

    points = torch.tensor(np.asarray(ds.points_xyz, np.float32), device=device)
    rgb = np.asarray(ds.points_rgb, np.float32)
    dist = knn_mean_sq_dist(points).sqrt()
    n = len(points)
    sh = torch.zeros((n, 16, 3), device=device)
    sh[:, 0] = torch.tensor(rgb_to_sh_dc(rgb), device=device)
    params = {"means": (points, 1.6e-4 * scene_scale), "scales": (torch.log(dist)[:, None].repeat(1, 3), 5e-3),
              "quats": (torch.rand((n, 4), device=device), 1e-3),
              "opacities": (torch.logit(torch.full((n,), 0.1, device=device)), 5e-2),
              "sh0": (sh[:, :1].clone(), 2.5e-3), "shN": (sh[:, 1:].clone(), 2.5e-3 / 20)}
    splats = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, (v, _) in params.items()})
    optimizers = {k: torch.optim.Adam([{"params": splats[k], "lr": lr, "name": k}], eps=1e-15, fused=True)
                  for k, (_, lr) in params.items()}
    return splats, optimizers


def as_raw(splats) -> dict:
    """The splats as our raw parameter arrays (numpy), for :meth:`Gaussians.from_numpy` and ``gsplat_peer``."""
    d = {k: v.detach().cpu().numpy() for k, v in splats.items()}
    return {"means": d["means"], "scales": d["scales"], "rotations": d["quats"], "opacities": d["opacities"],
            "sh_dc": d["sh0"][:, 0], "sh_rest": d["shN"]}


def evaluate(splats, ds, sh_degree: int) -> dict:
    """Test scores of gsplat's own renders and of the same model rendered by ours."""
    import torch

    import gsplat_peer
    import mi_gaussians as mig
    from mi_gaussians.evaluate import display, evaluate_views, summarize
    from mi_gaussians.metrics import psnr, ssim_np

    raw = as_raw(splats)
    p = gsplat_peer.to_torch(raw)
    ps, ss = [], []
    with torch.no_grad():
        for v in ds.test:
            target = v.load_image()[..., :3]
            rgb = gsplat_peer.rasterize(p, v.camera, background=ds.background, near_plane=0.01,
                                        sh_degree=sh_degree)[0].cpu().numpy()
            a, b = display(rgb, ds.color_space), display(target, ds.color_space)
            ps.append(psnr(a, b))
            ss.append(ssim_np(a, b))
    ours, _ = evaluate_views(mig.Gaussians.from_numpy(**raw), ds.test, tuple(ds.background), sh_degree=sh_degree,
                             with_lpips=False, color_space=ds.color_space)
    s = summarize(ours)
    # (per test view too: with a handful of test views one view can move the mean by a dB, so a comparison with
    # our run's metrics.json "views" is made view by view)
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "ours_psnr": s["psnr"], "ours_ssim": s["ssim"],
            "views": {v.name: {"psnr": float(p_), "ssim": float(s_)} for v, p_, s_ in zip(ds.test, ps, ss)}}


def train(ds, milestones: list[int], schedule: int, seed: int) -> list[dict]:
    import random

    import torch
    from gsplat import rasterization
    from gsplat.strategy import DefaultStrategy

    import gsplat_peer

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    scene_scale = float(ds.extent)
    splats, optimizers = init_splats(ds, scene_scale)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=0.01 ** (1.0 / schedule))
    strategy = DefaultStrategy()
    strategy.check_sanity(splats, optimizers)
    state = strategy.initialize_state(scene_scale=scene_scale)
    images = [torch.tensor(v.load_image()[..., :3], device="cuda")[None] for v in ds.train]
    cams = [gsplat_peer.camera_tensors(v.camera) for v in ds.train]
    bg = torch.tensor(np.asarray(ds.background, np.float32), device="cuda")[None]
    rng = np.random.default_rng(seed)
    order: list[int] = []
    rows, train_seconds = [], 0.0
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for step in range(max(milestones)):
        if not order:
            order = list(rng.permutation(len(images)))
        i = order.pop()
        cam = ds.train[i].camera
        sh_degree = min(step // 1000, 3)
        colors, _, info = rasterization(
            means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
            opacities=torch.sigmoid(splats["opacities"]), colors=torch.cat([splats["sh0"], splats["shN"]], 1),
            viewmats=cams[i][0], Ks=cams[i][1], width=cam.width, height=cam.height, sh_degree=sh_degree,
            near_plane=0.01, far_plane=1e10, packed=False, backgrounds=bg)
        strategy.step_pre_backward(splats, optimizers, state, step, info)
        l1 = (colors - images[i]).abs().mean()
        ssim = ssim_valid(colors.permute(0, 3, 1, 2), images[i].permute(0, 3, 1, 2))
        loss = torch.lerp(l1, 1.0 - ssim, 0.2)
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        scheduler.step()
        strategy.step_post_backward(splats, optimizers, state, step, info, packed=False)
        if step + 1 in milestones:
            torch.cuda.synchronize()
            train_seconds += time.perf_counter() - t0
            scores = evaluate(splats, ds, sh_degree)
            rows.append({"iterations": step + 1, **scores, "gaussians": int(splats["means"].shape[0]),
                         "minutes": train_seconds / 60.0, "it_s": (step + 1) / train_seconds})
            print(f"gsplat recipe, step {step + 1}: {rows[-1]}", file=sys.stderr, flush=True)
            torch.cuda.synchronize()
            t0 = time.perf_counter()
    return rows


def main(argv=None) -> int:
    from train import DATA, DATASETS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", choices=sorted(DATASETS))
    ap.add_argument("--milestones", type=int, nargs="+", default=[7000])
    ap.add_argument("--schedule", type=int, default=30000, help="simple_trainer's max_steps (its lr decay)")
    ap.add_argument("--variant", default="cuda_ad_rgb", help="our variant, for loading and the cross-check render")
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--out", default=None, help="write the rows as JSON here")
    ap.add_argument("--cache", default="/tmp/mi_gs_gsplat_train",
                    help="where initial points triangulated from the posed images are cached (CACHE/points)")
    args = ap.parse_args(argv)

    import gsplat_peer

    ok, why = gsplat_peer.available()
    if not ok:
        raise SystemExit(f"gsplat_train.py: {why}")
    import mitsuba as mi

    mi.set_variant(args.variant)
    folder, res, bg, note = DATASETS[args.dataset]
    if not (DATA / folder).exists():
        raise SystemExit(f"gsplat_train.py: {DATA / folder} is missing")
    # the points `mi-gs optimize` starts from with the same data settings (data.init 'auto': the layout's own, else
    # triangulated from the posed images, cached in --cache), so that both start from the same points
    from mi_gaussians.config import TrainConfig
    from mi_gaussians.runs import training_dataset

    cfg = TrainConfig().with_settings([f"data.resolution={res}", "data.background=" + ",".join(map(str, bg))])
    ds = training_dataset(DATA / folder, cfg, Path(args.cache), progress=False,
                          log=lambda line: print(line, file=sys.stderr, flush=True))
    print(f"{why}; {args.dataset} ({note}): {len(ds.train)} train / {len(ds.test)} test views, "
          f"{len(ds.points_xyz):,} points ({ds.points_from}), scene scale {ds.extent:.3f}", flush=True)
    rows = train(ds, sorted(args.milestones), max(args.schedule, max(args.milestones)), args.seed)
    print("\n| trainer | iterations | test PSNR | test SSIM | same model, our renderer | Gaussians | minutes | it/s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| gsplat simple_trainer recipe ({args.dataset}) | {r['iterations']:,} | {r['psnr']:.2f} | "
              f"{r['ssim']:.4f} | {r['ours_psnr']:.2f} / {r['ours_ssim']:.4f} | {r['gaussians']:,} | "
              f"{r['minutes']:.2f} | {r['it_s']:.0f} |")
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=2))
    return 0 if all(math.isfinite(r["psnr"]) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
