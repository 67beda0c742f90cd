"""Structure from motion for a folder of photos: the reference 3DGS ``convert.py`` with pycolmap instead of the COLMAP
binary (CPU only).

Steps (same as the reference): SIFT feature extraction with one shared camera (OPENCV model by default), exhaustive
matching, incremental mapping (global bundle adjustment tolerance 1e-6 as the reference passes), then undistortion
(``pycolmap.undistort_images``, COLMAP output) of the largest reconstruction. Result::

    out_dir/images/            undistorted images (PINHOLE camera)
    out_dir/sparse/0/          cameras.bin, images.bin, points3D.bin
    out_dir/distorted/         work folder: database.db, sparse/<k>/ (the distorted reconstructions)
    out_dir/images_{2,4,8}/    with resize=True: area-averaged copies, as the reference's --resize

so that ``load_dataset(out_dir)`` loads it. The input folder must not be ``out_dir/images``.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..config import ConvertConfig

_log = logging.getLogger(__name__)
_DEFAULTS = ConvertConfig()

_IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp"}


@dataclass(frozen=True)
class ConvertResult:
    """Summary of a :func:`convert` run."""

    out_dir: Path
    num_images: int                 # input images
    num_registered: int             # images with a pose in the kept reconstruction
    num_points: int                 # 3D points of the kept reconstruction
    mean_reprojection_error: float  # pixels
    num_models: int                 # reconstructions found (the largest is kept)
    focal: tuple[float, float] = (0.0, 0.0)   # fx, fy of the (first) undistorted camera, pixels

    def problems(self) -> list[str]:
        """What a user must hear about this reconstruction: few of the images registered (below
        :data:`WARN_REGISTERED`), focal lengths far apart (:data:`~mi_gaussians.data.camera.FOCAL_RATIO_LIMIT`)."""
        from .camera import FOCAL_RATIO_LIMIT

        out = []
        if self.num_registered < WARN_REGISTERED * self.num_images:
            out.append(f"structure from motion registered only {self.num_registered} of the {self.num_images} images "
                       f"({100 * self.num_registered / self.num_images:.0f} %); the scene holds those "
                       f"{self.num_registered} views only (too little overlap or texture between the others?)")
        fx, fy = self.focal
        if min(fx, fy) > 0 and max(fx, fy) / min(fx, fy) > FOCAL_RATIO_LIMIT:
            out.append(f"the reconstructed camera has fx {fx:.6g} and fy {fy:.6g}, a factor of "
                       f"{max(fx, fy) / min(fx, fy):.2f} apart (pixels that are not square): the reconstruction is "
                       "likely wrong")
        return out


#: fewer registered images than this share of the input is reported (:meth:`ConvertResult.problems`)
WARN_REGISTERED = 0.5
#: fewer registered images than this is an error: a scene needs training views and a test view
MIN_REGISTERED = 3


def list_images(images_dir: str | os.PathLike) -> list[str]:
    """Image file names (sorted) directly inside ``images_dir``."""
    d = Path(images_dir)
    return sorted(p.name for p in d.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)


def convert(images_dir: str | os.PathLike, out_dir: str | os.PathLike, *,
            camera_model: str = _DEFAULTS.camera_model, single_camera: bool = _DEFAULTS.single_camera,
            max_image_size: int = _DEFAULTS.max_image_size, max_num_features: int = _DEFAULTS.max_num_features,
            num_threads: int = _DEFAULTS.num_threads, resize: bool = _DEFAULTS.resize, overwrite: bool = False,
            seed: int = _DEFAULTS.seed, verbose: bool = False,
            progress: Callable[[str], None] | None = None) -> ConvertResult:
    """Run SfM on ``images_dir`` and write an undistorted COLMAP scene to ``out_dir`` (see the module docstring).

    camera_model: COLMAP model of the shared camera (reference: OPENCV); single_camera: one camera for all images;
    max_image_size / max_num_features: SIFT extraction limits (smaller = faster); num_threads: -1 = all cores;
    defaults from :class:`mi_gaussians.config.ConvertConfig`;
    resize: also write images_2/4/8; overwrite: replace an earlier result in ``out_dir`` (only the folders this
    function writes are removed); seed: mapper random seed; verbose: keep COLMAP's own INFO log lines on stderr
    (otherwise its log level is raised to ERROR for the duration of the call: its errors are ours, in one line);
    progress: called with one line per step (default: logging.info).

    Raises ValueError for a missing/empty input folder, fewer than 3 images, an existing result without ``overwrite``,
    or when no reconstruction of at least :data:`MIN_REGISTERED` images could be built. What the result's user must
    hear (few images registered, focal lengths far apart): :meth:`ConvertResult.problems`.
    """
    import pycolmap

    level = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = max(level, 2)      # (its errors too: ours name the problem in one line)
    try:
        return _convert(Path(images_dir), Path(out_dir), camera_model, single_camera, max_image_size,
                        max_num_features, num_threads, resize, overwrite, seed, progress or _log.info)
    finally:
        pycolmap.logging.minloglevel = level


def _convert(images_dir: Path, out_dir: Path, camera_model: str, single_camera: bool, max_image_size: int,
             max_num_features: int, num_threads: int, resize: bool, overwrite: bool, seed: int,
             say: Callable[[str], None]) -> ConvertResult:
    import pycolmap

    images_dir, out_dir = Path(images_dir).resolve(), Path(out_dir).resolve()
    if camera_model not in pycolmap.CameraModelId.__members__ or camera_model == "INVALID":
        raise ValueError(f"unknown COLMAP camera model {camera_model!r} (e.g. OPENCV, SIMPLE_RADIAL, PINHOLE)")
    if not images_dir.is_dir():
        raise ValueError(f"{images_dir}: input image folder not found")
    names = list_images(images_dir)
    if not names:
        raise ValueError(f"{images_dir}: no images (.jpg, .png, .tif, .bmp) in the folder")
    if len(names) < 3:
        raise ValueError(f"{images_dir}: too few images for structure from motion ({len(names)}; need at least 3)")
    if images_dir == out_dir / "images":
        raise ValueError(f"{images_dir}: the input folder cannot be out_dir/images (it receives the undistorted "
                         "images); put the photos in another folder, e.g. out_dir/input")
    outputs = [out_dir / "distorted", out_dir / "images", out_dir / "sparse", out_dir / "stereo"] + \
        [out_dir / f"images_{r}" for r in (2, 4, 8)]
    existing = [p for p in outputs if p.exists()]
    if existing and not overwrite:
        raise ValueError(f"{existing[0]}: already exists (pass overwrite=True to replace an earlier result)")
    for p in existing:
        shutil.rmtree(p)
    for p in out_dir.glob("run-colmap-*.sh"):     # written by the undistorter next to images/ and sparse/
        p.unlink()

    work = out_dir / "distorted"
    (work / "sparse").mkdir(parents=True)
    db = work / "database.db"
    device = pycolmap.Device.cpu

    say(f"[1/4] extracting SIFT features from {len(names)} images")
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_image_size
    extraction.num_threads = num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = max_num_features
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    pycolmap.extract_features(db, images_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO,
                              reader_options=reader, extraction_options=extraction, device=device)

    say(f"[2/4] exhaustive matching ({len(names) * (len(names) - 1) // 2} pairs)")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False
    pycolmap.match_exhaustive(db, matching_options=matching, device=device)

    say("[3/4] incremental mapping")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.min_model_size = min(opts.min_model_size, len(names))
    opts.ba_global_function_tolerance = 1e-6
    models = pycolmap.incremental_mapping(db, images_dir, work / "sparse", options=opts)
    if not models:
        raise ValueError(f"{images_dir}: structure from motion registered no images (too little overlap or texture)")
    best_key, best = max(models.items(), key=lambda kv: kv[1].num_reg_images())
    say(f"    {len(models)} reconstruction(s); keeping #{best_key}: {best.num_reg_images()}/{len(names)} images, "
        f"{best.num_points3D()} points, mean reprojection error {best.compute_mean_reprojection_error():.3f} px")
    if best.num_reg_images() < MIN_REGISTERED:
        raise ValueError(f"{images_dir}: structure from motion registered only {best.num_reg_images()} of the "
                         f"{len(names)} images (too little overlap or texture between them); a scene needs at least "
                         f"{MIN_REGISTERED} (its work folder {work} is kept)")

    say("[4/4] undistorting images")
    pycolmap.undistort_images(out_dir, work / "sparse" / str(best_key), images_dir, output_type="COLMAP",
                              num_threads=num_threads)
    sparse0 = out_dir / "sparse" / "0"
    sparse0.mkdir(parents=True, exist_ok=True)
    for f in list((out_dir / "sparse").iterdir()):
        if f.is_file():
            shutil.move(str(f), sparse0 / f.name)

    if resize:
        _write_reduced_copies(out_dir, say)
    result = pycolmap.Reconstruction(str(sparse0))
    say(f"done: {out_dir}")
    cam = next(iter(result.cameras.values()))
    return ConvertResult(out_dir, len(names), result.num_reg_images(), result.num_points3D(),
                         float(result.compute_mean_reprojection_error()), len(models),
                         (float(cam.focal_length_x), float(cam.focal_length_y)))


def _write_reduced_copies(out_dir: Path, say: Callable[[str], None]) -> None:
    """images_2, images_4, images_8: area-averaged copies at round(size / r), same file names and formats."""
    from PIL import Image

    src = out_dir / "images"
    names = list_images(src)
    for r in (2, 4, 8):
        say(f"    writing images_{r}")
        dst = out_dir / f"images_{r}"
        dst.mkdir()
        for n in names:
            with Image.open(src / n) as im:
                size = (max(1, round(im.width / r)), max(1, round(im.height / r)))
                im.convert("RGB").resize(size, Image.Resampling.BOX).save(dst / n, quality=95)
