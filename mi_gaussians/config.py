"""Every default of mi-gaussians, in frozen dataclasses (the only home of defaults).

Values follow the 3DGS paper and its reference implementation (see ``conventions.md``); where we differ on purpose,
the field's comment says so.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DataConfig:
    resolution: int = 1                      # -r: divide the image size by 1, 2, 4 or 8 (images_N folders when present)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # RGBA images are composited over this colour
    test_every: int = 8                      # COLMAP / single-transforms layouts: index % test_every == 0 is test (0: no test split)
    random_points: int = 100_000             # initial points for layouts without SfM points
    seed: int = 0


@dataclass(frozen=True)
class ConvertConfig:
    """Structure from motion (``mi_gaussians.data.convert``), the reference convert.py's choices on pycolmap."""

    camera_model: str = "OPENCV"             # COLMAP model of the shared camera (reference: OPENCV)
    single_camera: bool = True               # one camera for all images (reference: --ImageReader.single_camera 1)
    max_image_size: int = 3200               # SIFT extraction: larger images are downscaled (COLMAP 3.x default)
    max_num_features: int = 8192             # SIFT features per image (COLMAP's default)
    num_threads: int = -1                    # -1: all cores
    resize: bool = False                     # also write images_2/4/8 (reference: --resize)
    seed: int = 0                            # mapper random seed


@dataclass(frozen=True)
class RasterConfig:
    tile_size: int = 16
    near_plane: float = 0.2                  # cull Gaussians with view-space z <= near_plane
    guard_band: float = 1.3                  # the Jacobian clamps the projected mean to guard_band * tan(half fov)
    dilation: float = 0.3                    # low-pass filter added to the diagonal of the 2D covariance
    alpha_min: float = 1.0 / 255.0           # skip a Gaussian whose alpha is below this
    alpha_max: float = 0.99                  # clamp alpha
    transmittance_min: float = 1e-4          # stop before a Gaussian that would bring T below this
