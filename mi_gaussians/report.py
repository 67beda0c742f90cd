"""What a person looks at after a run: renders (EXR + PNG), side-by-side comparisons, metrics.json, curves."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .imwrite import display_encode, write_image, write_png
from .io_utils import atomic_path, atomic_write_text
from .run_folder import COMPARE, RENDERS


def error_image(render: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Per-pixel mean absolute error as a false-colour image (0 black .. 0.25+ white-hot)."""
    e = np.clip(np.abs(render - target).mean(axis=-1) / 0.25, 0.0, 1.0)
    return np.stack([np.clip(3 * e, 0, 1), np.clip(3 * e - 1, 0, 1), np.clip(3 * e - 2, 0, 1)], axis=-1)


def side_by_side(render: np.ndarray, target: np.ndarray) -> np.ndarray:
    """reference | render | error, display-encoded values in [0, 1]."""
    gap = np.ones((render.shape[0], 4, 3), np.float32)
    return np.concatenate([np.clip(target, 0, 1), gap, np.clip(render, 0, 1), gap, error_image(render, target)],
                          axis=1)


def write_view_outputs(out_dir: Path, scores, color_space: str) -> None:
    """renders/<name>.exr + .png and compare/<name>.png for every scored view (with images kept)."""
    for s in scores:
        stem = Path(s.name).stem
        write_image(out_dir / RENDERS / f"{stem}.exr", s.render, color_space)
        write_image(out_dir / RENDERS / f"{stem}.png", s.render, color_space)
        # compare what a person sees: the display-encoded images
        ref, img = display_encode(s.target, color_space), display_encode(s.render, color_space)
        write_png(out_dir / COMPARE / f"{stem}.png", side_by_side(img, ref))


def write_json(path: Path, data: dict) -> None:
    """``data`` as JSON (atomically); a non-finite number (a PSNR of identical images) is written as null, which
    JSON readers accept, where ``Infinity`` is not JSON."""
    atomic_write_text(path, json.dumps(_finite(data), indent=2, allow_nan=False) + "\n")


def _finite(x):
    if isinstance(x, float) and not np.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def plot_curves(path: Path, history: dict) -> None:
    """Training curves: loss, test PSNR and number of Gaussians against the iteration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    it, loss = history.get("iteration", []), history.get("loss", [])
    axes[0].plot(it, loss, lw=0.8)
    axes[0].set_yscale("log")
    axes[0].set_title("training loss (L1 + D-SSIM)")
    ev = history.get("eval_iteration", [])
    axes[1].plot(ev, history.get("test_psnr", []), marker="o")
    axes[1].set_title("test PSNR (dB)")
    axes[2].plot(it, history.get("gaussians", []))
    axes[2].set_title("number of Gaussians")
    for a in axes:
        a.set_xlabel("iteration")
        a.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
