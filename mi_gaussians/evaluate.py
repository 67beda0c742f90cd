"""Render a set of views with a model and score them against their images (PSNR, SSIM, LPIPS when available)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import RasterConfig
from .metrics import lpips_available, lpips_vgg, psnr, ssim_np
from .model.gaussians import Gaussians
from .raster.rasterize import render


@dataclass
class ViewScore:
    name: str
    psnr: float
    ssim: float
    lpips: float | None = None
    render: np.ndarray | None = field(default=None, repr=False)   # (H, W, 3) float32, as rendered
    target: np.ndarray | None = field(default=None, repr=False)


def evaluate_views(g: Gaussians, views, background, sh_degree: int | None = None,
                   cfg: RasterConfig = RasterConfig(), keep_images: bool = False, with_lpips: bool = True,
                   targets: dict | None = None) -> tuple[list[ViewScore], str | None]:
    """Scores per view and a note on LPIPS (None when it was computed).

    ``targets`` optionally maps view names to already-loaded images (avoids decoding them again)."""
    use_lpips, note = lpips_available() if with_lpips else (False, "LPIPS not requested")
    scores = []
    for v in views:
        target = targets[v.name] if targets is not None and v.name in targets else v.load_image()
        img = np.array(render(g, v.camera, background=background, sh_degree=sh_degree, cfg=cfg).rgb,
                       dtype=np.float32).reshape(target.shape)
        img = np.clip(img, 0.0, 1.0)           # the reference scores clamp(render, 0, 1)
        s = ViewScore(name=v.name, psnr=psnr(img, target), ssim=ssim_np(img, target),
                      lpips=lpips_vgg(img, target) if use_lpips else None)
        if keep_images:
            s.render, s.target = img, target
        scores.append(s)
    return scores, (None if use_lpips else note)


def summarize(scores: list[ViewScore]) -> dict:
    out = {"psnr": float(np.mean([s.psnr for s in scores])) if scores else None,
           "ssim": float(np.mean([s.ssim for s in scores])) if scores else None}
    if scores and all(s.lpips is not None for s in scores):
        out["lpips"] = float(np.mean([s.lpips for s in scores]))
    return out
