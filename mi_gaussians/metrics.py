"""Image-quality metrics of the 3DGS evaluation: PSNR, SSIM and (when available offline) LPIPS-VGG.

Scores on NumPy images; SSIM runs the Dr.Jit kernels of :mod:`mi_gaussians.image_ops` that the training loss uses.

All functions take NumPy-convertible float images of shape (H, W, 3) (or (H, W, C)) with values in [0, 1] and return
Python floats for one image pair; averaging over the test views is the caller's job (the reference averages per-image
scores).

Clamping: the reference scores ``clamp(render, 0, 1)`` (``train.py``'s report) or 8-bit PNG renders (``metrics.py``,
whose values are in [0, 1] by construction); every function here clamps both images to [0, 1] first (pass
``clamp=False`` to score raw values). The PNG quantization of ``metrics.py`` is not reproduced: scores are computed
on the float renders.
"""

from __future__ import annotations

import functools
import importlib.util
import math
import os

import numpy as np

from .drjit_utils import owned_tensor
from .image_ops import LUMA, REFERENCE_SSIM, SSIMParams, gaussian_window, ssim

# torchvision's ImageNet VGG16 weights (the file torch.hub caches for ``vgg16(weights=IMAGENET1K_V1)``)
VGG16_WEIGHTS_FILE = "vgg16-397923af.pth"


def _pair(img, ref, clamp: bool) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(img, dtype=np.float64)
    b = np.asarray(ref, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images of different shapes: {a.shape} and {b.shape}")
    if a.ndim not in (2, 3) or a.size == 0:
        raise ValueError(f"expected (H, W, C) or (H, W) images, got shape {a.shape}")
    if clamp:
        a, b = np.clip(a, 0.0, 1.0), np.clip(b, 0.0, 1.0)
    return a, b


def psnr(img, ref, clamp: bool = True) -> float:
    """Peak signal-to-noise ratio in dB for a peak of 1: ``20 log10(1 / sqrt(MSE))``, the MSE taken over every pixel
    and channel (the reference's ``utils.image_utils.psnr`` on one image). Identical images give ``inf``."""
    a, b = _pair(img, ref, clamp)
    mse = float(np.mean((a - b) ** 2))
    if mse == 0.0:
        return math.inf
    return 20.0 * math.log10(1.0 / math.sqrt(mse))


def _jit_variant() -> bool:
    import mitsuba as mi

    v = mi.variant()
    return v is not None and (v.startswith("llvm_") or v.startswith("cuda_"))


def ssim_float64(a: np.ndarray, b: np.ndarray, params: SSIMParams = REFERENCE_SSIM) -> float:
    """The reference SSIM in float64 with SciPy (zero padding, separable Gaussian window), for (H, W, C) arrays."""
    from scipy.ndimage import correlate1d

    g = np.asarray(gaussian_window(params.window, params.sigma))
    c1, c2 = params.c1, params.c2

    def blur(v):
        return correlate1d(correlate1d(v, g, axis=0, mode="constant"), g, axis=1, mode="constant")

    mu1, mu2 = blur(a), blur(b)
    s11, s22, s12 = blur(a * a) - mu1 ** 2, blur(b * b) - mu2 ** 2, blur(a * b) - mu1 * mu2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s11 + s22 + c2))
    return float(m.mean())


def ssim_np(img, ref, clamp: bool = True) -> float:
    """Mean SSIM (the reference's 11 x 11 Gaussian window, sigma 1.5, zero padding), as the training loss computes it.

    Runs the training loss's Dr.Jit kernels (:func:`mi_gaussians.image_ops.ssim`) when a JIT Mitsuba variant is
    active, so the metric and the loss agree; otherwise a float64 NumPy/SciPy port of the same formula (they agree to
    ~1e-6)."""
    a, b = _pair(img, ref, clamp)
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if not _jit_variant():
        return ssim_float64(a, b)
    return float(ssim(owned_tensor(a), owned_tensor(b))[0])


# ----------------------------------------------------------------------------------------------------------- LPIPS
def _lpips_paths() -> tuple[str | None, str | None, str]:
    """(VGG16 backbone weights file, LPIPS linear-layer weights file, reason if unavailable)."""
    if importlib.util.find_spec("torch") is None:
        return None, None, "LPIPS unavailable: torch is not installed"
    if importlib.util.find_spec("lpips") is None:
        return None, None, "LPIPS unavailable: the 'lpips' package is not installed"
    if importlib.util.find_spec("torchvision") is None:
        return None, None, "LPIPS unavailable: torchvision is not installed"
    import torch

    backbone = os.path.join(torch.hub.get_dir(), "checkpoints", VGG16_WEIGHTS_FILE)
    if not os.path.isfile(backbone):
        return None, None, (f"LPIPS unavailable: the VGG16 weights are not in the torch hub cache ({backbone}; set "
                            f"TORCH_HOME or place {VGG16_WEIGHTS_FILE} there; nothing is downloaded)")
    spec = importlib.util.find_spec("lpips")
    linear = os.path.join(os.path.dirname(spec.origin), "weights", "v0.1", "vgg.pth")
    if not os.path.isfile(linear):
        return None, None, f"LPIPS unavailable: the lpips package lacks its linear weights ({linear})"
    return backbone, linear, ""


@functools.lru_cache(maxsize=1)
def _lpips_model():
    """(model, None) or (None, reason): LPIPS-VGG built offline, the backbone loaded from the torch hub cache."""
    backbone, _, reason = _lpips_paths()
    if backbone is None:
        return None, reason
    try:
        import lpips
        import torch

        try:
            model = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True, verbose=False)   # random backbone
        except TypeError:                                   # older lpips without ``verbose``
            model = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True)
        state = torch.load(backbone, map_location="cpu", weights_only=True)
        feats = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
        loaded = 0
        for slice_name in ("slice1", "slice2", "slice3", "slice4", "slice5"):
            for idx, module in getattr(model.net, slice_name).named_children():   # named by the features index
                for pname, p in module.named_parameters(recurse=False):
                    with torch.no_grad():
                        p.copy_(feats[f"{idx}.{pname}"])
                    loaded += 1
        if loaded != 26:                                    # 13 convolutions x (weight, bias)
            return None, f"LPIPS unavailable: loaded {loaded} of the 26 VGG16 tensors LPIPS uses"
        model.eval()
        return model, None
    except Exception as e:                                  # any failure means "unavailable", never a crash
        return None, f"LPIPS unavailable: {type(e).__name__}: {e}".splitlines()[0]


def lpips_available() -> tuple[bool, str]:
    """(True, "") when LPIPS-VGG can run offline (torch, torchvision and the ``lpips`` package installed, the
    ImageNet VGG16 weights already in the torch hub cache), else (False, one-line reason). Never downloads."""
    model, reason = _lpips_model()
    return (True, "") if model is not None else (False, reason)


def lpips_vgg(img, ref, clamp: bool = True, convention: str = "3dgs") -> float:
    """LPIPS with the VGG16 backbone (lower is better); raises RuntimeError when :func:`lpips_available` is False.

    ``convention``: "3dgs" feeds the [0, 1] images unchanged, exactly as the reference's ``metrics.py`` does
    (``lpips(render, gt, net_type='vgg')`` on ``to_tensor`` images, although the network's input scaling assumes
    [-1, 1]); use it to compare with published 3DGS numbers. "lpips" maps them to [-1, 1] (``2 x - 1``), the input
    range the LPIPS authors specify. The two give different values."""
    if convention not in ("3dgs", "lpips"):
        raise ValueError(f"convention must be '3dgs' or 'lpips', got {convention!r}")
    model, reason = _lpips_model()
    if model is None:
        raise RuntimeError(reason)
    import torch

    a, b = _pair(img, ref, clamp)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"LPIPS needs RGB (H, W, 3) images, got shape {a.shape}")

    def tensor(v):
        t = torch.from_numpy(np.ascontiguousarray(v.transpose(2, 0, 1)[None], dtype=np.float32))
        return t * 2.0 - 1.0 if convention == "lpips" else t

    with torch.no_grad():
        return float(model(tensor(a), tensor(b)).item())


# ------------------------------------------------------------------------------------------ colour transforms
def fit_affine(render: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The 3 x 4 colour transform ``E`` minimizing the squared error of ``render @ E[:, :3] + E[:, 3]`` against
    ``target`` over every pixel of the (..., 3) arrays (linear least squares in float64): the transform the 2024
    reference's exposure compensation fits (``optim/exposure.py`` has the layout)."""
    x = np.asarray(render, np.float64).reshape(-1, 3)
    y = np.asarray(target, np.float64).reshape(-1, 3)
    design = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    s, *_ = np.linalg.lstsq(design, y, rcond=None)        # (4, 3): s[k, j] weighs input channel k (then 1) in j
    return np.concatenate([s[:3], s[3][:, None]], axis=1)


def apply_affine(image: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``image`` (..., 3) through the 3 x 4 transform ``e``: ``image @ e[:, :3] + e[:, 3]`` (float32)."""
    e = np.asarray(e, np.float64)
    return (np.asarray(image, np.float64) @ e[:, :3] + e[:, 3]).astype(np.float32)


def apply_bilateral(image: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``image`` (H, W, 3) through the bilateral grid ``grid`` (L, GH, GW, 3, 4) of transforms in
    :func:`apply_affine`'s layout: each pixel's transform trilinearly interpolated at its centre's (x, y) and its
    BT.601 luma clamped to [0, 1], as ``optim/bilateral.py`` applies it in training (float32)."""
    img = np.asarray(image, np.float64)
    g = np.asarray(grid, np.float64)
    levels, gh, gw = g.shape[:3]
    h, w = img.shape[:2]

    def split(coord, n):
        i0 = np.minimum(np.floor(coord).astype(np.int64), n - 2)
        return i0, coord - i0

    x0, fx = split((np.arange(w) + 0.5) * ((gw - 1) / w), gw)
    y0, fy = split((np.arange(h) + 0.5) * ((gh - 1) / h), gh)
    z0, fz = split(np.clip(img @ np.array(LUMA), 0.0, 1.0) * (levels - 1), levels)
    e = np.zeros((h, w, 3, 4))
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                weight = ((fz if dz else 1 - fz) * (fy if dy else 1 - fy)[:, None]
                          * (fx if dx else 1 - fx)[None, :])
                e += weight[..., None, None] * g[z0 + dz, (y0 + dy)[:, None], (x0 + dx)[None, :]]
    return (np.einsum("hwr,hwrj->hwj", img, e[..., :3]) + e[..., 3]).astype(np.float32)


def apply_compensation(image: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``image`` (H, W, 3) through a training image's colour compensation: a 3 x 4 transform (``--exposure``) or a
    bilateral grid of them (``--exposure bilateral``)."""
    return apply_affine(image, t) if np.ndim(t) == 2 else apply_bilateral(image, t)
