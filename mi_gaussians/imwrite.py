"""Writing renders: linear float EXR and 8-bit sRGB PNG, atomically, plus sRGB <-> linear transfer functions.

A render is in the colour space its model was trained in: 3DGS models fitted to PNG/JPEG photographs hold
sRGB-encoded values, models fitted to EXR references hold linear radiance. ``write_image`` takes that colour space
and writes what each format means: EXR files are linear, PNG files are sRGB-encoded (8-bit).
"""

from __future__ import annotations

import os

import numpy as np

from .io_utils import atomic_path

COLOR_SPACES = ("srgb", "linear")

# The sRGB transfer curve (IEC 61966-2-1): linear segment below the thresholds, offset power curve above. Also used by
# the Dr.Jit decoder of the ``gaussian_splatting`` integrator (mi_gaussians.plugins.splat_integrator).
SRGB_DECODE_THRESHOLD = 0.04045     # encoded value where the linear segment ends
SRGB_ENCODE_THRESHOLD = 0.0031308   # linear value where the linear segment ends
SRGB_SLOPE = 12.92                  # slope of the linear segment
SRGB_OFFSET = 0.055                 # encoded = (1 + offset) linear^(1 / gamma) - offset
SRGB_GAMMA = 2.4


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values -> linear (float32; the power curve continues above 1)."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= SRGB_DECODE_THRESHOLD, x / SRGB_SLOPE,
                    ((np.maximum(x, SRGB_DECODE_THRESHOLD) + SRGB_OFFSET) / (1.0 + SRGB_OFFSET)) ** SRGB_GAMMA
                    ).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values -> sRGB-encoded (float32; the power curve continues above 1)."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= SRGB_ENCODE_THRESHOLD, x * SRGB_SLOPE,
                    (1.0 + SRGB_OFFSET) * np.maximum(x, SRGB_ENCODE_THRESHOLD) ** (1 / SRGB_GAMMA) - SRGB_OFFSET
                    ).astype(np.float32)


def display_encode(img: np.ndarray, color_space: str = "srgb") -> np.ndarray:
    """What a person sees, before clipping: linear images are sRGB-encoded (negative values set to 0 first); images
    that already are sRGB-encoded are returned unchanged."""
    if color_space == "linear":
        return linear_to_srgb(np.maximum(img, 0.0))
    return img


def to_uint8(x: np.ndarray) -> np.ndarray:
    return (np.clip(np.nan_to_num(x, nan=0.0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_exr(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write (H, W), (H, W, 3) or (H, W, 4) float32 as an uncompressed-float (ZIP) EXR: Y, RGB or RGBA."""
    import OpenEXR

    img = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    if img.ndim == 2:
        channels = {"Y": img}
    elif img.ndim == 3 and img.shape[2] in (3, 4):
        names = "RGBA"[: img.shape[2]]
        channels = {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate(names)}
    else:
        raise ValueError(f"{os.fspath(path)}: cannot write an image of shape {img.shape} as EXR")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, suffix=".exr") as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write (H, W), (H, W, 3) or (H, W, 4) values in [0, 1] (already display-encoded) as an 8-bit PNG."""
    from PIL import Image

    img = to_uint8(np.asarray(image))
    with atomic_path(path, suffix=".png") as tmp:
        Image.fromarray(img).save(tmp, format="PNG")


def write_image(path: str | os.PathLike, image: np.ndarray, color_space: str = "srgb") -> None:
    """Write by extension: ``.exr`` gets linear values, ``.png`` sRGB-encoded ones (converted as needed)."""
    if color_space not in COLOR_SPACES:
        raise ValueError(f"unknown colour space {color_space!r} (expected one of {COLOR_SPACES})")
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    img = np.asarray(image, dtype=np.float32)
    rgb, rest = (img[..., :3], img[..., 3:]) if img.ndim == 3 else (img, None)
    if ext == ".exr":
        if color_space == "srgb":
            rgb = srgb_to_linear(rgb)
        write_exr(path, np.concatenate([rgb, rest], axis=-1) if rest is not None and rest.size else rgb)
    elif ext == ".png":
        if color_space == "linear":
            rgb = linear_to_srgb(rgb)
        write_png(path, np.concatenate([rgb, rest], axis=-1) if rest is not None and rest.size else rgb)
    else:
        raise ValueError(f"{path}: unsupported output format {ext or '(none)'} (use .exr or .png)")
