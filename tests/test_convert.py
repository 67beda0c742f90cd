"""``convert``: structure from motion with pycolmap on scenes/turntable_images (16 views, 200x200)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from mi_gaussians.data.convert import convert
from mi_gaussians.data.dataset import load_dataset

IMAGES = Path(__file__).parents[1] / "scenes" / "turntable_images"


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    out = tmp_path_factory.mktemp("turntable")
    messages: list[str] = []
    t = time.perf_counter()
    result = convert(IMAGES, out, num_threads=2, max_num_features=2048, resize=True, progress=messages.append)
    return out, result, messages, time.perf_counter() - t


def test_convert_turntable(converted):
    import pycolmap

    out, result, messages, seconds = converted
    assert seconds < 30.0
    assert result.num_images == 16
    # all 16 register in practice; allow a little slack for thread-order effects in the mapper
    assert result.num_registered >= 14, result
    assert result.num_points > 300 and result.mean_reprojection_error < 1.0
    assert any(m.startswith("[1/4]") for m in messages) and messages[-1].startswith("done")
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_reg_images() == result.num_registered
    assert all(c.model.name == "PINHOLE" for c in rec.cameras.values())
    assert (out / "distorted" / "database.db").is_file()


def test_converted_scene_loads(converted):
    out, result, _, _ = converted
    ds = load_dataset(out)
    assert ds.layout == "colmap"
    assert len(ds.train) + len(ds.test) == result.num_registered
    assert ds.points_xyz.shape == (result.num_points, 3)
    img = ds.train[0].load_image()
    assert img.shape == (ds.train[0].camera.height, ds.train[0].camera.width, 3)
    # the cameras look at the middle of the scene: the centroid of the points projects inside every image
    centre = ds.points_xyz.mean(axis=0)
    for v in ds.views:
        (u, w), z = (a[0] for a in v.camera.project(centre[None]))
        assert z > 0 and 0 <= u < v.camera.width and 0 <= w < v.camera.height
    # resize=True wrote images_2/4/8, used by load_dataset(resolution=r)
    ds4 = load_dataset(out, resolution=4)
    assert ds4.train[0].image_path.parent.name == "images_4"
    assert ds4.train[0].load_image().shape[:2] == (ds4.train[0].camera.height, ds4.train[0].camera.width)


def test_convert_refuses_to_overwrite(converted, tmp_path):
    out, _, _, _ = converted
    with pytest.raises(ValueError, match=r"already exists \(pass overwrite=True"):
        convert(IMAGES, out)


def test_convert_input_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"empty: no images"):
        convert(tmp_path / "empty", tmp_path / "out")
    with pytest.raises(ValueError, match=r"input image folder not found"):
        convert(tmp_path / "missing", tmp_path / "out")
    few = tmp_path / "few"
    few.mkdir()
    for name in sorted(p.name for p in IMAGES.iterdir())[:2]:
        shutil.copy(IMAGES / name, few / name)
    with pytest.raises(ValueError, match=r"too few images for structure from motion \(2; need at least 3\)"):
        convert(few, tmp_path / "out")
    inside = tmp_path / "scene" / "images"
    shutil.copytree(IMAGES, inside)
    with pytest.raises(ValueError, match=r"the input folder cannot be out_dir/images"):
        convert(inside, inside.parent)
    with pytest.raises(ValueError, match=r"unknown COLMAP camera model 'FOO'"):
        convert(IMAGES, tmp_path / "out", camera_model="FOO")


def test_convert_nothing_registered(tmp_path):
    """Featureless images: no reconstruction, a clear error."""
    from PIL import Image

    flat = tmp_path / "flat"
    flat.mkdir()
    rng = np.random.default_rng(0)
    for k in range(4):
        Image.new("RGB", (64, 64), tuple(int(c) for c in rng.integers(0, 255, 3))).save(flat / f"{k}.png")
    with pytest.raises(ValueError, match=r"flat: structure from motion registered no images"):
        convert(flat, tmp_path / "out", num_threads=2)
