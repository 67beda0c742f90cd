"""Render a set of views with a model and score them against their images (PSNR, SSIM, LPIPS when available)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import RasterConfig
from .imwrite import display_encode
from .metrics import apply_affine, fit_affine, lpips_available, lpips_vgg, psnr, ssim_np
from .model.gaussians import Gaussians
from .raster.rasterize import render


@dataclass
class ViewScore:
    name: str
    psnr: float
    ssim: float
    lpips: float | None = None
    render: np.ndarray | None = field(default=None, repr=False)   # (H, W, 3) float32, as rendered (>= 0)
    target: np.ndarray | None = field(default=None, repr=False)


def display(img: np.ndarray, color_space: str = "srgb") -> np.ndarray:
    """What the metrics compare: the display-encoded image (:func:`mi_gaussians.imwrite.display_encode`: linear images
    are sRGB-encoded first), float32, clipped to [0, 1]."""
    return np.clip(display_encode(np.asarray(img, dtype=np.float32), color_space), 0.0, 1.0)


#: The protocols a view is scored by: the whole image as rendered, or the 2024 reference's for exposure compensation.
PROTOCOLS = {
    "full": "the whole image, as rendered",
    "half": "a 3x4 colour transform fitted by least squares on the left half of each view, then the right half "
            "scored (the 2024 reference's --train_test_exp evaluation)",
}


def evaluate_views(g: Gaussians, views, background, sh_degree: int | None = None,
                   cfg: RasterConfig = RasterConfig(), keep_images: bool = False, with_lpips: bool = True,
                   targets: dict | None = None, color_space: str = "srgb",
                   protocol: str = "full") -> tuple[list[ViewScore], str | None]:
    """Scores per view and a note on LPIPS (None when it was computed).

    Metrics compare display images (:func:`display`): renders and references clipped to [0, 1] as the reference
    scores ``clamp(render, 0, 1)``; with ``color_space='linear'`` (models of linear radiance) both are sRGB-encoded
    first, so that PSNR means the same for a model trained on radiance and one trained on encoded values.
    ``targets`` optionally maps view names to already-loaded images (avoids decoding them again). ``protocol``: one
    of :data:`PROTOCOLS` ('half': the colour transform is fitted in the colour space the model was trained in, as
    the training-time transforms work)."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown evaluation protocol {protocol!r} (expected one of {', '.join(PROTOCOLS)})")
    use_lpips, note = lpips_available() if with_lpips else (False, "LPIPS not requested")
    scores = []
    for v in views:
        target = targets[v.name] if targets is not None and v.name in targets else v.load_image()
        out = render(g, v.camera, background=background, sh_degree=sh_degree, cfg=cfg, depth=False)
        img = np.array(out.rgb, dtype=np.float32).reshape(target.shape)
        if protocol == "half":
            half = target.shape[1] // 2
            e = fit_affine(img[:, :half], target[:, :half, :3])
            img, target = apply_affine(img[:, half:], e), target[:, half:]
        a, b = display(img, color_space), display(target, color_space)
        s = ViewScore(name=v.name, psnr=psnr(a, b), ssim=ssim_np(a, b), lpips=lpips_vgg(a, b) if use_lpips else None)
        if keep_images:
            s.render, s.target = np.maximum(img, 0.0), target
        scores.append(s)
    return scores, (None if use_lpips else note)


def summarize(scores: list[ViewScore]) -> dict:
    out = {"psnr": float(np.mean([s.psnr for s in scores])) if scores else None,
           "ssim": float(np.mean([s.ssim for s in scores])) if scores else None}
    if scores and all(s.lpips is not None for s in scores):
        out["lpips"] = float(np.mean([s.lpips for s in scores]))
    return out


def scores_report(scores: list[ViewScore], lpips_note: str | None = None) -> dict:
    """The metrics record of a set of scored views, as ``metrics.json`` and ``eval.json`` hold it: ``mean``
    (:func:`summarize`), ``views`` (name -> psnr, ssim and lpips when computed) and ``lpips_note`` when LPIPS was not
    computed. Callers add their own fields (split, number of Gaussians, timings)."""
    out = {"mean": summarize(scores),
           "views": {s.name: {"psnr": s.psnr, "ssim": s.ssim, **({"lpips": s.lpips} if s.lpips is not None else {})}
                     for s in scores}}
    if lpips_note:
        out["lpips_note"] = lpips_note
    return out


def depth_error(g: Gaussians, views, cfg: RasterConfig = RasterConfig()) -> dict | None:
    """Mean absolute error of the rendered expected depth against the views' exact depth (Mitsuba scenes), over the
    pixels where the reference sees a surface and the render covers the pixel (alpha > 0.5), in scene units;
    ``coverage``: the fraction of the reference's surface pixels that the render covers. None without depth."""
    total, count, surface = 0.0, 0, 0
    for v in views:
        ref = v.load_depth()
        if ref is None:
            return None
        out = render(g, v.camera, cfg=cfg)
        d, a = np.array(out.depth, np.float64), np.array(out.alpha, np.float64)
        hit = np.isfinite(ref) & (ref > 0)
        ok = hit & (a > 0.5)
        total += float(np.abs(d[ok] - ref[ok]).sum())
        count += int(ok.sum())
        surface += int(hit.sum())
    if not surface:
        return None
    return {"depth_mae": total / count if count else None, "coverage": count / surface}
