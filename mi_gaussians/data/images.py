"""Image files -> float32 arrays: read (PNG/JPEG/EXR), composite RGBA, downsample, undistort.

Values are kept in the file's own encoding, like the reference 3DGS loader: PNG/JPEG give ``value / 255`` (sRGB-encoded,
*not* linearized; 16-bit PNG ``value / 65535`` at full precision, through pypng where Pillow would keep 8 bits), EXR
gives linear floats. A dataset's ``color_space`` says which.

Alpha: PNG alpha is straight (un-premultiplied, as in NeRF-synthetic): ``rgb * a + bg * (1 - a)``. EXR alpha is
premultiplied (OpenEXR's convention, and what Mitsuba writes): ``rgb + bg * (1 - a)``. A separate mask file (white =
object, e.g. a capture's segmentation) is a straight coverage applied after the file's own alpha:
``rgb * m + bg * (1 - m)``, alpha ``a * m``; its grey value (mean of R, G, B, not linearized) is ``m``.

Downsampling is an area average (Pillow's BOX filter on float data): exact block means for integer factors, area-weighted
for others. The reference resizes with Pillow's default (bicubic); area averaging does not alias or ring.

Undistortion follows COLMAP's image undistorter: the pinhole camera is the one ``pycolmap.undistort_camera`` chooses
(default options: no blank pixels), and each pixel centre of the undistorted image is mapped through that pinhole camera
to a normalized ray and through the distorted camera back to the source image, then sampled bilinearly. We do the
sampling ourselves (scipy) so that float and RGBA images keep their precision (``pycolmap.Bitmap`` is 8-bit RGB only);
the tests compare the result with ``pycolmap.undistort_image``.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Extensions tried, in this order, for a ``file_path`` given without one (NeRF-synthetic writes "./train/r_0").
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".PNG", ".JPG", ".JPEG", ".EXR")


def color_space_of(path: str | os.PathLike) -> str:
    """'linear' for EXR files, 'srgb' for everything else (PNG, JPEG)."""
    return "linear" if os.fspath(path).lower().endswith(".exr") else "srgb"


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file from its header only (no pixel decoding)."""
    path = os.fspath(path)
    if color_space_of(path) == "linear":
        import OpenEXR

        try:
            lo, hi = OpenEXR.File(path, header_only=True).header()["dataWindow"]
        except Exception as e:  # OpenEXR raises RuntimeError with a long message
            raise ValueError(f"{path}: cannot read the EXR header ({str(e).splitlines()[0]})") from None
        return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except FileNotFoundError:
        raise ValueError(f"{path}: image file not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as e:   # (Pillow: SyntaxError for a broken PNG chunk)
        raise ValueError(f"{path}: not a readable image ({e})") from None


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Decode an image file to (H, W, C) float32, C = 3 (RGB) or 4 (RGBA); greyscale is expanded to RGB."""
    path = os.fspath(path)
    if color_space_of(path) == "linear":
        return _read_exr(path)
    if _png_16_bit_colour(path):
        return _read_png_16(path)
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode in ("I;16", "I;16B", "I;16L", "I"):
                a = np.asarray(im).astype(np.float32) / 65535.0    # 16-bit greyscale PNG
                arr = np.repeat(a[..., None], 3, axis=2)
            elif mode == "F":
                arr = np.repeat(np.asarray(im).astype(np.float32)[..., None], 3, axis=2)
            else:
                has_alpha = mode in ("RGBA", "LA", "PA", "La", "RGBa") or "transparency" in im.info
                rgb = im.convert("RGBA" if has_alpha else "RGB")
                # np.asarray(im, dtype=float32) takes a slow element-wise path: convert the uint8 array instead
                arr = np.asarray(rgb).astype(np.float32) / 255.0
    except FileNotFoundError:
        raise ValueError(f"{path}: image file not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as e:   # (Pillow: SyntaxError for a broken PNG chunk)
        raise ValueError(f"{path}: not a readable image ({e})") from None
    return np.ascontiguousarray(arr, dtype=np.float32)


def _png_16_bit_colour(path: str) -> bool:
    """Whether ``path`` is a PNG of 16 bits per sample with colour or alpha (Pillow would cut it to 8 bits)."""
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return False
    return head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and head[24] == 16 and head[25] in (2, 4, 6)


def _read_png_16(path: str) -> np.ndarray:
    """A 16-bit RGB, RGBA or grey + alpha PNG at full precision (pypng): (H, W, 3 or 4) float32 ``value / 65535``."""
    import png

    try:
        width, height, rows, info = png.Reader(filename=path).asDirect()
        a = np.vstack([np.asarray(r, dtype=np.uint16) for r in rows]).reshape(height, width, info["planes"])
    except (png.Error, OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable image ({e})") from None
    a = a.astype(np.float32) / 65535.0
    if info["greyscale"]:                        # (grey + alpha)
        a = np.concatenate([np.repeat(a[..., :1], 3, axis=2), a[..., 1:]], axis=2)
    return np.ascontiguousarray(a)


def _read_exr(path: str) -> np.ndarray:
    import OpenEXR

    try:
        f = OpenEXR.File(path, separate_channels=True)
    except Exception as e:
        raise ValueError(f"{path}: cannot read the EXR file ({str(e).splitlines()[0]})") from None
    ch = {name: c.pixels for name, c in f.channels().items()}
    if all(k in ch for k in ("R", "G", "B")):
        planes = [ch["R"], ch["G"], ch["B"]] + ([ch["A"]] if "A" in ch else [])
    elif "Y" in ch:
        planes = [ch["Y"]] * 3 + ([ch["A"]] if "A" in ch else [])
    else:
        raise ValueError(f"{path}: EXR has no R, G, B (or Y) channels (found {sorted(ch)})")
    return np.ascontiguousarray(np.stack([np.asarray(p, dtype=np.float32) for p in planes], axis=2))


def composite(image: np.ndarray, background, premultiplied: bool) -> np.ndarray:
    """(H, W, 4) RGBA -> (H, W, 3) RGB over ``background`` (3,); RGB input is returned unchanged (as float32).

    straight alpha: ``rgb * a + bg * (1 - a)``; premultiplied: ``rgb + bg * (1 - a)``.
    """
    if image.shape[2] == 3:
        return image.astype(np.float32, copy=False)
    rgb, a = image[..., :3], image[..., 3:4]
    bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
    out = (rgb if premultiplied else rgb * a) + bg * (1.0 - a)
    return out.astype(np.float32)


def read_mask(path: str | os.PathLike, size: tuple[int, int]) -> np.ndarray:
    """A mask file -> (H, W) float32 coverage in [0, 1] at ``size`` (width, height): the mean of its R, G, B (its own
    alpha is ignored), area-resampled when the file has another size."""
    m = read_image(path)[..., :3].mean(axis=2, keepdims=True, dtype=np.float32)
    return resize_area(m, *size)[..., 0]


def resize_area(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-average (Pillow BOX) resampling of (H, W, C) float32 to (height, width, C) float32."""
    h, w = image.shape[:2]
    if (w, h) == (width, height):
        return image
    from PIL import Image

    planes = [np.asarray(Image.fromarray(np.ascontiguousarray(image[..., k], dtype=np.float32), mode="F")
                         .resize((width, height), Image.Resampling.BOX), dtype=np.float32)
              for k in range(image.shape[2])]
    return np.stack(planes, axis=2)


class Undistorter:
    """One distorted COLMAP camera and the pinhole camera COLMAP's undistorter gives it (full resolution).

    ``model`` is a COLMAP model name, ``params`` its parameters in COLMAP order, ``width``/``height`` the size of the
    images the parameters belong to. Sampling grids are cached per output/source size (one instance is shared by all
    views of a camera; the cache is the only mutable state and is guarded by a lock).
    """

    def __init__(self, model: str, width: int, height: int, params, source: str = "camera"):
        import pycolmap

        try:
            cam = pycolmap.Camera(model=model, width=int(width), height=int(height),
                                  params=[float(p) for p in params])
        except Exception as e:
            raise ValueError(f"{source}: invalid {model} camera ({e})") from None
        if not cam.verify_params():
            raise ValueError(f"{source}: {model} camera has {len(list(params))} parameters, "
                             f"expected {cam.params_info}")
        self.model = model
        self.distorted = cam
        try:
            pin = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
        except Exception as e:
            raise ValueError(f"{source}: COLMAP cannot undistort this {model} camera ({e})") from None
        fx, fy, cx, cy = (float(v) for v in pin.params)
        if pin.width <= 0 or pin.height <= 0 or not np.all(np.isfinite([fx, fy, cx, cy])):
            raise ValueError(f"{source}: COLMAP cannot undistort this {model} camera (degenerate result)")
        self.pinhole = (int(pin.width), int(pin.height), fx, fy, cx, cy)
        self._grids: dict[tuple[int, int, int, int], np.ndarray] = {}
        self._lock = threading.Lock()

    def __getstate__(self):
        # picklable (e.g. for worker processes): drop the lock and the cached grids
        return {k: v for k, v in self.__dict__.items() if k not in ("_grids", "_lock")}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._grids = {}
        self._lock = threading.Lock()

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the distorted images."""
        return int(self.distorted.width), int(self.distorted.height)

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Normalized camera coordinates (N, 2) -> full-resolution distorted pixel coordinates (N, 2)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.asarray(self.distorted.img_from_cam(np.c_[xy, np.ones(len(xy))], check_cheirality=False))

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Full-resolution distorted pixel coordinates (N, 2) -> full-resolution undistorted ones (N, 2)."""
        n = np.asarray(self.distorted.cam_from_img(np.asarray(uv, dtype=np.float64).reshape(-1, 2)))
        _, _, fx, fy, cx, cy = self.pinhole
        return np.c_[fx * n[:, 0] + cx, fy * n[:, 1] + cy]

    def grid(self, out_size: tuple[int, int], src_size: tuple[int, int]) -> np.ndarray:
        """Sampling grid (2, out_h, out_w) of (row, col) array indices into a source image of ``src_size``.

        The output image is the undistorted pinhole image resampled to ``out_size``; the source image is the distorted
        image resampled to ``src_size``. Both resamplings scale pixel coordinates per axis."""
        key = (*out_size, *src_size)
        with self._lock:
            g = self._grids.get(key)
        if g is not None:
            return g
        pw, ph, fx, fy, cx, cy = self.pinhole
        ow, oh = out_size
        sw, sh = src_size
        dw, dh = self.size
        j, i = np.mgrid[0:oh, 0:ow]
        u = (i.ravel() + 0.5) * (pw / ow)            # full-resolution undistorted pixel coordinates
        v = (j.ravel() + 0.5) * (ph / oh)
        d = self.distort_normalized(np.c_[(u - cx) / fx, (v - cy) / fy])
        col = d[:, 0] * (sw / dw) - 0.5              # array index: pixel centre at +0.5
        row = d[:, 1] * (sh / dh) - 0.5
        g = np.stack([row.reshape(oh, ow), col.reshape(oh, ow)]).astype(np.float32)
        with self._lock:
            self._grids[key] = g
        return g

    def undistort(self, image: np.ndarray, out_size: tuple[int, int]) -> np.ndarray:
        """Undistort (H, W, C) float32 (the distorted image at any resolution) to (out_h, out_w, C) float32.

        Bilinear sampling; samples outside the source clamp to its border (COLMAP's default options choose the output
        so that there are none, up to half a pixel)."""
        from scipy.ndimage import map_coordinates

        h, w = image.shape[:2]
        g = self.grid(out_size, (w, h))
        out = [map_coordinates(image[..., k], g, order=1, mode="nearest") for k in range(image.shape[2])]
        return np.stack(out, axis=2).astype(np.float32, copy=False)


@dataclass(frozen=True)
class ImageLoader:
    """How one view's image file becomes the (H, W, 3) float32 array of its camera.

    Steps: read -> composite RGBA over ``background`` (then through ``mask_path``, when set, see the module
    docstring) -> area-resample to ``source_size`` -> undistort to ``size``
    (when ``undistorter`` is set; otherwise ``source_size == size``). ``size`` and ``source_size`` are (width, height).
    """

    size: tuple[int, int]
    source_size: tuple[int, int]
    background: tuple[float, float, float]
    undistorter: Undistorter | None = field(default=None, compare=False, repr=False)
    mask_path: Path | None = None

    def load(self, path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
        """(rgb (H, W, 3) float32, alpha (H, W) float32 or None when the file has no alpha and there is no mask)."""
        raw = read_image(path)
        premultiplied = color_space_of(path) == "linear"
        rgb = composite(raw, self.background, premultiplied)
        alpha = raw[..., 3:4] if raw.shape[2] == 4 else None
        if self.mask_path is not None:
            m = read_mask(self.mask_path, (raw.shape[1], raw.shape[0]))[..., None]
            rgb = composite(np.concatenate([rgb, m], axis=2), self.background, premultiplied=False)
            alpha = m if alpha is None else alpha * m
        img = rgb if alpha is None else np.concatenate([rgb, alpha], axis=2)
        img = resize_area(img, *self.source_size)
        if self.undistorter is not None:
            img = self.undistorter.undistort(img, self.size)
        if (img.shape[1], img.shape[0]) != tuple(self.size):
            raise ValueError(f"{os.fspath(path)}: loaded image is {img.shape[1]}x{img.shape[0]}, "
                             f"expected {self.size[0]}x{self.size[1]}")
        alpha = img[..., 3] if img.shape[2] == 4 else None
        return np.ascontiguousarray(img[..., :3]), alpha


def _is_file(p: Path) -> bool:
    """``p.is_file()``, False also for names the OS cannot even look up (too long, NUL bytes)."""
    try:
        return p.is_file()
    except (OSError, ValueError):
        return False


def resolve_image_file(base: Path, file_path: str) -> tuple[Path, bool]:
    """Resolve a transforms.json ``file_path`` (with or without extension) against ``base``.

    Returns (path, exists); when nothing exists, the path is the one the caller should name in an error."""
    p = (base / file_path)
    if p.suffix in IMAGE_EXTENSIONS and _is_file(p):
        return p, True
    for ext in IMAGE_EXTENSIONS:
        q = p.with_name(p.name + ext)
        if _is_file(q):
            return q, True
    if _is_file(p):
        return p, True
    return (p if p.suffix.lower() in {e.lower() for e in IMAGE_EXTENSIONS} else p.with_name(p.name + ".png")), False
