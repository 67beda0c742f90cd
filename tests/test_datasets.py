"""Dataset loading: layouts, camera conventions on real data, resolution, undistortion, compositing, EXR, errors.

Real-data tests use ../shared/data (skipped when absent); the tiny scenes in tests/data are built by
tests/data/make_fixtures.py.
"""

from __future__ import annotations

import csv
import struct
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mi_gaussians.data.dataset import detect_layout, load_dataset
from mi_gaussians.data.images import Undistorter, read_image, resize_area

DATA = Path(__file__).parent / "data"


def need(shared_data: Path, rel: str) -> Path:
    p = shared_data / rel
    if not p.exists():
        pytest.skip(f"{p} is not available")
    return p


def copy_fixture(name: str, tmp_path: Path) -> Path:
    dst = tmp_path / name
    shutil.copytree(DATA / name, dst)
    return dst


# ------------------------------------------------------------------------------------------------ COLMAP conventions
def observations(rec, image, max_points: int | None = None):
    """(3D points (N, 3), their 2D observations (N, 2)) of one pycolmap image."""
    obs = [p for p in image.points2D if p.has_point3D()][:max_points]
    xyz = np.array([rec.points3D[p.point3D_id].xyz for p in obs]).reshape(-1, 3)
    uv = np.array([p.xy for p in obs]).reshape(-1, 2)
    return xyz, uv


@pytest.mark.parametrize("rel", ["mi_objects/colmap", "mi_room/colmap"])
def test_colmap_reprojection_pinhole(shared_data, rel):
    """Every COLMAP observation is reproduced by projecting its 3D point with OUR camera (from load_dataset) to within
    the SfM noise (README: mean 0.73 / 0.52 px), and our projection equals pycolmap's own to 1e-6 px."""
    import pycolmap

    root = need(shared_data, rel)
    ds = load_dataset(root)
    by_name = {v.name: v for v in ds.views}
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    errors = []
    for image in rec.images.values():
        cam = by_name[image.name].camera
        xyz, uv = observations(rec, image)
        ours, z = cam.project(xyz)
        assert np.all(z > 0)
        theirs = np.array([image.project_point(p) for p in xyz[:20]])
        np.testing.assert_allclose(ours[:20], theirs, atol=1e-6)
        errors.append(np.linalg.norm(ours - uv, axis=1))
    errors = np.concatenate(errors)
    assert len(errors) > 1000
    assert errors.mean() < 1.0, f"mean reprojection error {errors.mean():.3f} px"


def test_colmap_reprojection_undistorted_maryrose(shared_data):
    """maryrose has a SIMPLE_RADIAL camera; views get the PINHOLE camera of the undistorted image.

    Observations are distorted pixel coordinates; we map them into the undistorted image with COLMAP's own inverse
    distortion (``pycolmap.Camera.cam_from_img``, then the undistorted pinhole intrinsics) and compare them with our
    projection of the 3D points: the error is the SfM noise (0.80 px in the model). We also check our projection against
    pycolmap's distorted projection mapped the same way (exact), at full resolution and at -r 8."""
    import pycolmap

    root = need(shared_data, "maryrose")
    ds = load_dataset(root)
    ds8 = load_dataset(root, resolution=8)
    by_name = {v.name: v for v in ds.views}
    by_name8 = {v.name: v for v in ds8.views}
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    und = ds.train[0].loader.undistorter
    assert und is not None and und.model == "SIMPLE_RADIAL"
    errors = []
    for k, image in enumerate(sorted(rec.images.values(), key=lambda i: i.name)):
        if k % 7:
            continue                                   # 10 of the 69 images keep the test fast
        cam = by_name[image.name].camera
        assert (cam.width, cam.height) == (3454, 3454)   # COLMAP's undistorted size
        xyz, uv = observations(rec, image, max_points=3000)
        ours, _ = cam.project(xyz)
        errors.append(np.linalg.norm(ours - und.undistort_points(uv), axis=1))
        exact = und.undistort_points(np.array([image.project_point(p) for p in xyz[:30]]))
        np.testing.assert_allclose(ours[:30], exact, atol=1e-3)
        cam8 = by_name8[image.name].camera
        assert (cam8.width, cam8.height) == (432, 432)
        ours8, _ = cam8.project(xyz[:30])
        np.testing.assert_allclose(ours8, exact * [432 / 3454, 432 / 3454], atol=1e-3)
    errors = np.concatenate(errors)
    assert errors.mean() < 1.0, f"mean reprojection error {errors.mean():.3f} px"


def test_tiny_colmap_exact(tmp_path):
    """The tiny text model's observations are exact projections: our cameras reproduce them to 1e-9 px."""
    import pycolmap

    ds = load_dataset(DATA / "tiny_colmap", test_every=0)
    rec = pycolmap.Reconstruction(str(DATA / "tiny_colmap" / "sparse" / "0"))
    assert [v.name for v in ds.train] == ["a.png", "b.png", "c.png"]
    for v in ds.train:
        assert (v.camera.cx, v.camera.cy) == (11.5, 7.25)
        image = rec.find_image_with_name(v.name)
        xyz, uv = observations(rec, image)
        np.testing.assert_allclose(v.camera.project(xyz)[0], uv, atol=1e-9)
    assert ds.points_xyz.shape == (6, 3) and ds.points_xyz.dtype == np.float32
    assert ds.points_rgb.dtype == np.float32 and ds.points_rgb.max() <= 1.0
    # the loader's pose is pycolmap's cam_from_world
    image = rec.find_image_with_name("b.png")
    w2c = np.eye(4)
    w2c[:3, :4] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
    np.testing.assert_allclose(w2c, ds.train[1].camera.world_to_camera, rtol=0, atol=1e-12)


def _compare_with_pycolmap(model_dir: Path) -> None:
    import pycolmap

    from mi_gaussians.data.colmap import read_model

    ours, rec = read_model(model_dir), pycolmap.Reconstruction(str(model_dir))
    assert sorted(ours.cameras) == sorted(rec.cameras)
    for cid, c in rec.cameras.items():
        o = ours.cameras[cid]
        assert (o.model, o.width, o.height) == (c.model.name, c.width, c.height)
        assert o.params == tuple(float(p) for p in c.params)
    assert sorted(i.image_id for i in ours.images) == sorted(k for k, v in rec.images.items() if v.has_pose)
    for o in ours.images:
        im = rec.images[o.image_id]
        assert (o.name, o.camera_id) == (im.name, im.camera_id)
        np.testing.assert_allclose(o.world_to_camera[:3], np.asarray(im.cam_from_world().matrix()), rtol=0, atol=1e-12)
    ids = sorted(rec.points3D)          # COLMAP writes points in id order; we keep the file's order
    np.testing.assert_array_equal(ours.points_xyz, np.array([rec.points3D[i].xyz for i in ids], np.float32))
    np.testing.assert_array_equal(ours.points_rgb,
                                  np.array([rec.points3D[i].color for i in ids], np.float32) / np.float32(255.0))


@pytest.mark.parametrize("rel", ["mi_objects/colmap", "mi_room/colmap", "maryrose"])
def test_colmap_reader_matches_pycolmap(shared_data, rel, tmp_path):
    """Our COLMAP parser (text and binary) reads exactly what pycolmap reads, on every shared COLMAP model, in the
    model's own format and in the other one (written by pycolmap)."""
    import pycolmap

    root = shared_data / rel / "sparse" / "0"
    if not root.is_dir():
        pytest.skip(f"{root} is missing")
    _compare_with_pycolmap(root)
    other = tmp_path / "other"
    other.mkdir()
    rec = pycolmap.Reconstruction(str(root))
    if (root / "cameras.bin").is_file():
        rec.write_text(str(other))
    else:
        rec.write_binary(str(other))
    _compare_with_pycolmap(other)


# ------------------------------------------------------------------------------------------------ Blender / splits
def read_views_csv(root: Path) -> list[dict]:
    with open(root / "views.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("scene", ["mi_objects", "mi_room"])
def test_blender_and_colmap_layouts_agree(shared_data, scene):
    """views.csv maps COLMAP names to Blender files: the same view gets the same camera from both layouts, and the
    splits are the documented ones."""
    root = need(shared_data, scene)
    col = load_dataset(root / "colmap")
    bl = load_dataset(root / "blender")
    assert (col.layout, bl.layout) == ("colmap", "blender")
    cams_c = {v.name: v.camera for v in col.views}
    cams_b = {v.name: v.camera for v in bl.views}
    rows = read_views_csv(root)
    assert len(rows) == len(cams_c) == len(cams_b)
    for row in rows:
        a, b = cams_c[row["colmap_name"]], cams_b[row["blender_file"]]
        np.testing.assert_allclose(a.world_to_camera, b.world_to_camera, atol=1e-5)
        np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy, a.width, a.height],
                                   [b.fx, b.fy, b.cx, b.cy, b.width, b.height], rtol=1e-7)
    assert {v.name for v in col.test} == {r["colmap_name"] for r in rows if r["colmap_split_llffhold8"] == "test"}
    assert {v.name for v in bl.test} == {r["blender_file"] for r in rows if r["blender_split"] == "test"}
    held = (root / "colmap" / "test_images_llffhold8.txt").read_text().split()
    assert sorted(v.name for v in col.test) == sorted(held)
    assert col.points_xyz is not None and len(col.points_xyz) > 1000
    # extent: 1.1 x max distance of train centres from their mean
    c = np.stack([v.camera.center for v in col.train])
    assert col.extent == pytest.approx(1.1 * np.linalg.norm(c - c.mean(0), axis=1).max())
    np.testing.assert_allclose(col.center, c.mean(0))


def test_blender_pose_by_rendering(shared_data, bright_sphere):
    """A bright sphere at a known world point, rendered by Mitsuba from a Blender view's camera (to_mitsuba), lands
    where Camera.project puts it; the Blender file's pose therefore matches Mitsuba's geometry of the dataset."""
    root = need(shared_data, "mi_objects/blender")
    ds = load_dataset(root, test_every=0)
    for view in (ds.train[0], ds.train[57]):
        for p in ([0.3, -0.2, 0.5], [-0.6, 0.4, 0.1]):
            img = bright_sphere.render(view.camera, p, radius=0.04, spp=32)
            uv, _ = view.camera.project(np.array([p]))
            np.testing.assert_allclose(bright_sphere.centroid(img), uv[0], atol=0.5)


def test_blender_compositing_matches_colmap_images(shared_data):
    """mi_objects' colmap/images are the Blender RGBA images composited over white in 8-bit sRGB values: our loader
    with background=(1, 1, 1) reproduces them to 8-bit rounding."""
    root = need(shared_data, "mi_objects")
    bl = load_dataset(root / "blender", background=(1.0, 1.0, 1.0))
    col = {v.name: v for v in load_dataset(root / "colmap").views}
    by_file = {r["blender_file"]: r["colmap_name"] for r in read_views_csv(root)}
    for view in bl.train[:3]:
        ours = view.load_image()
        theirs = col[by_file[view.name]].load_image()
        assert ours.shape == (200, 200, 3) and ours.dtype == np.float32
        assert np.abs(ours - theirs).max() <= 1.0 / 255 + 1e-6
        alpha = view.load_alpha()
        assert alpha.shape == (200, 200) and 0.0 < alpha.mean() < 1.0


def test_tiny_blender_layout_and_compositing():
    ds = load_dataset(DATA / "tiny_blender", background=(0.2, 0.4, 0.6))
    assert ds.layout == "blender" and ds.color_space == "srgb"
    assert [v.name for v in ds.train] == ["train/r_0.png", "train/r_1.png"]
    assert [v.name for v in ds.test] == ["test/r_0.png"]
    v = ds.train[1]
    assert (v.camera.width, v.camera.height, v.camera.cx, v.camera.cy) == (24, 16, 11.5, 7.25)
    raw = np.asarray(Image.open(v.image_path)).astype(np.float32) / 255
    expect = raw[..., :3] * raw[..., 3:] + np.array([0.2, 0.4, 0.6], np.float32) * (1 - raw[..., 3:])
    np.testing.assert_allclose(v.load_image(), expect, atol=1e-6)
    np.testing.assert_allclose(v.load_alpha(), raw[..., 3], atol=1e-7)
    assert ds.points_xyz.shape == (100_000, 3) and np.abs(ds.points_xyz).max() <= 1.3
    # test_every=0 merges the test views into train (the reference without --eval)
    assert len(load_dataset(DATA / "tiny_blender", test_every=0).train) == 3
    # seeded: same points for the same seed
    np.testing.assert_array_equal(load_dataset(DATA / "tiny_blender", random_points=10, seed=3).points_xyz,
                                  load_dataset(DATA / "tiny_blender", random_points=10, seed=3).points_xyz)


def test_blender_file_path_with_extension_and_camera_angle_only(tmp_path):
    """file_path may carry its extension; without fl_x/cx/cy/w/h the reference's camera_angle_x rule applies."""
    root = copy_fixture("tiny_blender", tmp_path)
    for split in ("train", "test"):
        p = root / f"transforms_{split}.json"
        d = json.loads(p.read_text())
        d = {"camera_angle_x": d["camera_angle_x"],
             "frames": [{**f, "file_path": f["file_path"] + ".png"} for f in d["frames"]]}
        p.write_text(json.dumps(d))
    ds = load_dataset(root)
    cam = ds.train[0].camera
    assert (cam.width, cam.height, cam.cx, cam.cy) == (24, 16, 12.0, 8.0)
    assert cam.fx == pytest.approx(20.0) and cam.fy == pytest.approx(20.0)


# ------------------------------------------------------------------------------------------------ resolution
def test_resolution_area_average_and_scaled_camera(tmp_path):
    full = load_dataset(DATA / "tiny_colmap", test_every=0)
    half = load_dataset(DATA / "tiny_colmap", test_every=0, resolution=2)
    a, b = full.train[0], half.train[0]
    assert (b.camera.width, b.camera.height) == (12, 8)
    assert b.camera.fx == a.camera.fx / 2 and b.camera.cx == a.camera.cx / 2 and b.camera.cy == a.camera.cy / 2
    img = a.load_image()
    np.testing.assert_allclose(b.load_image(), img.reshape(8, 2, 12, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    # non-integer ratio: 24x16 / 5 -> round(4.8) x round(3.2) = 5 x 3, intrinsics scaled per axis
    c = load_dataset(DATA / "tiny_colmap", test_every=0, resolution=5).train[0].camera
    assert (c.width, c.height) == (5, 3)
    assert c.fx == pytest.approx(20 * 5 / 24) and c.fy == pytest.approx(20 * 3 / 16)


def test_colmap_prefers_images_r_folder(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    (root / "images_2").mkdir()
    for p in (root / "images").iterdir():
        Image.new("RGB", (12, 8), (255, 0, 0)).save(root / "images_2" / p.name)
    v = load_dataset(root, resolution=2).train[0]
    assert v.image_path.parent.name == "images_2"
    np.testing.assert_array_equal(v.load_image()[..., 0], 1.0)
    (root / "images_2" / "a.png").unlink()
    Image.new("RGB", (10, 8)).save(root / "images_2" / "a.png")
    with pytest.raises(ValueError, match=r"images_2/a\.png: image is 10x8"):
        load_dataset(root, resolution=2)


def test_ngp_reads_images_r_folder(tmp_path, caplog):
    """ngp (nerfstudio's downscaled folders): at -r 2 an images_2/ folder beside transforms.json is read in place of
    resampling images/, its files named like the frames' images; the view is the same camera (undistorted as
    before) and the image the undistortion of the reduced file. Without images/ the frames stay (only images_2 is
    needed); a frame missing in images_2 is skipped as a missing image is."""
    root = copy_fixture("tiny_ngp", tmp_path)
    plain = load_dataset(root, test_every=0, resolution=2)
    (root / "images_2").mkdir()
    for v in plain.train:
        full = np.asarray(Image.open(v.image_path).convert("RGB"))
        Image.fromarray(full[::2, ::2]).save(root / "images_2" / v.image_path.name)
    ds = load_dataset(root, test_every=0, resolution=2)
    assert [v.name for v in ds.train] == [v.name for v in plain.train]
    for a, b in zip(plain.train, ds.train):
        assert b.image_path.parent.name == "images_2"
        assert (b.camera.width, b.camera.height, b.camera.fx, b.camera.cx) == \
            (a.camera.width, a.camera.height, a.camera.fx, a.camera.cx)
        expect = b.loader.undistorter.undistort(
            np.asarray(Image.open(b.image_path).convert("RGB"), dtype=np.float32) / 255.0, (b.camera.width,
                                                                                              b.camera.height))
        np.testing.assert_allclose(b.load_image(), expect, atol=1e-6)
    shutil.rmtree(root / "images")
    assert len(load_dataset(root, test_every=0, resolution=2).train) == len(plain.train)
    (root / "images_2" / Path(plain.train[0].image_path).name).unlink()
    with caplog.at_level(logging.WARNING):
        left = load_dataset(root, test_every=0, resolution=2)
    assert len(left.train) == len(plain.train) - 1 and "skipping 2 of 5 frames" in caplog.text
    with pytest.raises(ValueError, match=r"none of the 5 frames"):  # at -r 1 images/ is needed again
        load_dataset(root, test_every=0)


def test_blender_images_r_keeps_train_and_test_apart(tmp_path):
    """A Blender scene's train/r_0.png and test/r_0.png share a name: images_2/ holds them at their relative paths
    (images_2/train/r_0.png), so neither view reads the other's image."""
    root = copy_fixture("tiny_blender", tmp_path)
    plain = load_dataset(root, resolution=2)
    colours = {"train": (255, 0, 0), "test": (0, 0, 255)}
    for split, views in (("train", plain.train), ("test", plain.test)):
        for v in views:
            rel = v.image_path.relative_to(root)
            assert rel.parts[0] == split
            w, h = Image.open(v.image_path).size
            (root / "images_2" / rel).parent.mkdir(parents=True, exist_ok=True)
            Image.new("RGB", (round(w / 2), round(h / 2)), colours[split]).save(root / "images_2" / rel)
    ds = load_dataset(root, resolution=2)
    assert {v.image_path.parent.name for v in ds.train} == {"train"} and ds.test
    assert np.all(ds.train[0].load_image()[..., 0] == 1.0) and np.all(ds.test[0].load_image()[..., 2] == 1.0)


def write_masks(root: Path, names: dict[str, str], size=(24, 16), seed=0) -> dict[str, np.ndarray]:
    """Random grey masks for the tiny COLMAP scene's images, saved as ``masks/<file name>``; returns name -> m (H, W)."""
    rng = np.random.default_rng(seed)
    (root / "masks").mkdir(exist_ok=True)
    out = {}
    for image, fname in names.items():
        m8 = rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8)
        m8[0, 0], m8[0, 1] = 0, 255
        Image.fromarray(m8, mode="L").save(root / "masks" / fname)
        out[image] = m8.astype(np.float32) / 255.0
    return out


def test_colmap_masks_composite_over_background_and_become_alpha(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    # the three naming conventions: same name, COLMAP's NAME.png, and <stem>_mask.<ext>
    ms = write_masks(root, {"a.png": "a.png", "b.png": "b.png.png", "c.png": "c_mask.png"})
    bg = np.array([0.2, 0.4, 0.6], np.float32)
    plain = load_dataset(root, test_every=0, background=bg, masks=False)
    masked = load_dataset(root, test_every=0, background=bg)
    for p, v in zip(plain.train, masked.train):
        assert p.loader.mask_path is None and v.loader.mask_path is not None
        m = ms[v.name][..., None]
        img = v.load_image()
        np.testing.assert_allclose(img, p.load_image() * m + bg * (1 - m), atol=1e-6)
        np.testing.assert_array_equal(img[0, 0], bg)                  # mask 0: the background exactly
        np.testing.assert_array_equal(img[0, 1], p.load_image()[0, 1])  # mask 1: the image exactly
        np.testing.assert_allclose(v.load_alpha(), m[..., 0], atol=1e-7)
        np.testing.assert_array_equal(p.load_alpha(), 1.0)
    # at 1/2 resolution the masked image and alpha are the block means of the full-resolution ones (area average)
    half = load_dataset(root, test_every=0, background=bg, resolution=2)
    for full, v in zip(masked.train, half.train):
        np.testing.assert_allclose(v.load_image(), full.load_image().reshape(8, 2, 12, 2, 3).mean(axis=(1, 3)),
                                   atol=1e-6)
        np.testing.assert_allclose(v.load_alpha(), full.load_alpha().reshape(8, 2, 12, 2).mean(axis=(1, 3)),
                                   atol=1e-6)


def test_colmap_masks_with_images_r_folder(tmp_path):
    """images_2/ takes masks_2/ when there is one, else the full-size masks/ resampled to the image."""
    root = copy_fixture("tiny_colmap", tmp_path)
    (root / "images_2").mkdir()
    for p in (root / "images").iterdir():
        Image.new("RGB", (12, 8), (255, 255, 255)).save(root / "images_2" / p.name)
    ms = write_masks(root, {n: n for n in ("a.png", "b.png", "c.png")})
    v = load_dataset(root, resolution=2, test_every=0).train[0]
    assert v.loader.mask_path == root / "masks" / "a.png"
    np.testing.assert_allclose(v.load_alpha(), ms["a.png"].reshape(8, 2, 12, 2).mean(axis=(1, 3)), atol=1e-6)
    np.testing.assert_allclose(v.load_image()[..., 0], v.load_alpha(), atol=1e-6)       # white over black
    (root / "masks_2").mkdir()
    for n in ("a.png", "b.png", "c.png"):
        Image.new("L", (12, 8), 0).save(root / "masks_2" / n)
    v = load_dataset(root, resolution=2, test_every=0).train[0]
    assert v.loader.mask_path == root / "masks_2" / "a.png"
    np.testing.assert_array_equal(v.load_image(), 0.0)


def test_error_colmap_masks_missing_or_wrong_size(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    write_masks(root, {"a.png": "a.png", "c.png": "c.png"})
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{root / 'masks' / 'b.png'}: no mask for {root / 'images' / 'b.png'}")
    assert len(load_dataset(root, masks=False).views) == 3                  # masks=False ignores the folder
    write_masks(root, {"b.png": "b.png"}, size=(20, 16))
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e) == (f"{root / 'masks' / 'b.png'}: mask is 20x16, but its image {root / 'images' / 'b.png'} "
                           "is 24x16")
    with pytest.raises(ValueError, match="masks must be True or False"):
        load_dataset(root, masks="yes")


def test_area_resize_of_float_images():
    rng = np.random.default_rng(1)
    img = rng.random((16, 24, 4)).astype(np.float32)
    np.testing.assert_allclose(resize_area(img, 3, 2), img.reshape(2, 8, 3, 8, 4).mean(axis=(1, 3)), atol=1e-6)


# ------------------------------------------------------------------------------------------------ undistortion
@pytest.mark.parametrize("model, params", [
    ("SIMPLE_RADIAL", (150.0, 77.3, 61.2, 0.15)),
    ("RADIAL", (140.0, 80.0, 60.0, -0.1, 0.02)),
    ("OPENCV", (150.0, 152.0, 83.1, 57.4, 0.1, -0.05, 0.002, -0.001)),
])
def test_undistortion_matches_pycolmap(model, params):
    """Our float undistortion equals pycolmap.undistort_image (8-bit) up to its rounding, same camera and size."""
    import pycolmap

    rng = np.random.default_rng(0)
    g = rng.random((12, 16, 3)).astype(np.float32)
    img = np.stack([np.asarray(Image.fromarray(g[..., c], mode="F").resize((160, 120), Image.Resampling.BICUBIC))
                    for c in range(3)], axis=2)
    img8 = (np.clip(img, 0, 1) * 255).round().astype(np.uint8)
    u = Undistorter(model, 160, 120, params)
    ours = u.undistort(img8.astype(np.float32) / 255, u.pinhole[:2])
    bitmap, cam = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(img8),
                                           u.distorted)
    assert (cam.width, cam.height) == u.pinhole[:2]
    np.testing.assert_allclose(cam.params, u.pinhole[2:])
    ref = bitmap.to_array().astype(np.float32) / 255
    assert ours.shape == ref.shape
    assert np.abs(ours - ref).max() <= 0.5 / 255 + 1e-4


def test_tiny_ngp_distortion_camera_geometry(caplog):
    """ngp with OpenCV distortion: the view camera is the undistorted pinhole; a 3D point projects with it to where
    the distorted OpenCV camera (pycolmap) puts it, mapped through undistortion and the resolution scaling."""
    import pycolmap

    with caplog.at_level(logging.WARNING):
        ds = load_dataset(DATA / "tiny_ngp", test_every=0, resolution=2)
    assert "skipping 1 of 5 frames" in caplog.text and "images/0003.png" in caplog.text
    assert [v.name for v in ds.train] == ["images/0000.png", "images/0001.png", "images/0002.png", "images/0004.png"]
    meta = json.loads((DATA / "tiny_ngp" / "transforms.json").read_text())
    dist = pycolmap.Camera(model="OPENCV", width=24, height=16,
                           params=[meta[k] for k in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2")])
    und = ds.train[0].loader.undistorter
    pw, ph = und.pinhole[:2]
    for v in ds.train:
        cam = v.camera
        assert (cam.width, cam.height) == (round(pw / 2), round(ph / 2))
        pts_cam = np.array([[0.1, -0.05, 1.0], [-0.2, 0.1, 1.5], [0.0, 0.0, 2.0]])
        pts = (cam.camera_to_world @ np.c_[pts_cam, np.ones(3)].T).T[:, :3]
        uv_dist = dist.img_from_cam(pts_cam)
        expect = und.undistort_points(uv_dist) * [cam.width / pw, cam.height / ph]
        np.testing.assert_allclose(cam.project(pts)[0], expect, atol=1e-6)
        assert v.load_image().shape == (cam.height, cam.width, 3)
    assert ds.points_xyz.shape == (100_000, 3)


def test_fox_ngp_reduced_resolution(shared_data, caplog):
    root = need(shared_data, "fox")
    with caplog.at_level(logging.WARNING):
        ds = load_dataset(root, resolution=4)
    assert ds.layout == "ngp"
    assert "skipping 17 of 67 frames" in caplog.text
    assert len(ds.train) + len(ds.test) == 50 and len(ds.test) == 7
    names = sorted(v.name for v in ds.views)
    assert "images/0005.jpg" not in names and names[0] == "images/0001.jpg"
    cam = ds.train[0].camera
    assert (cam.width, cam.height) == (267, 474)          # COLMAP's undistorted 1067 x 1897, / 4
    assert cam.cx != cam.width / 2 and cam.cy != cam.height / 2
    img = ds.train[0].load_image()
    assert img.shape == (474, 267, 3) and img.dtype == np.float32 and 0.0 <= img.min() and img.max() <= 1.0
    assert ds.points_xyz.shape == (100_000, 3)


def test_maryrose_reduced_resolution(shared_data):
    root = need(shared_data, "maryrose")
    t = time.perf_counter()
    ds = load_dataset(root, resolution=8)
    assert time.perf_counter() - t < 5.0, "validation must read image headers only"
    assert (len(ds.train), len(ds.test)) == (60, 9)
    assert ds.points_xyz.shape == (62250, 3)
    v = ds.test[0]
    assert v.name == "IMG_9669.JPG"
    img = v.load_image()
    assert img.shape == (432, 432, 3) and v.camera.fx == pytest.approx(10536.036 * 432 / 3454, rel=1e-6)
    # the turntable's masks (white = tankard) are used: the background is the dataset's, the mask the alpha
    assert v.loader.mask_path == root / "masks" / "IMG_9669_mask.JPG"
    alpha = v.load_alpha()
    assert alpha.shape == (432, 432) and alpha[0, 0] < 0.01 and alpha[216, 216] > 0.99
    assert 0.1 < alpha.mean() < 0.9
    np.testing.assert_allclose(img[alpha < 1e-3], 0.0, atol=1e-3)          # composited over black (the default)
    plain = load_dataset(root, resolution=8, masks=False).test[0]
    assert plain.loader.mask_path is None and plain.load_image()[alpha < 1e-3].mean() > 0.05


# ------------------------------------------------------------------------------------------------ EXR
def write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    """Write float32 channels. OpenEXR's Python writer ignores numpy strides: pass contiguous planes."""
    import OpenEXR

    planes = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    OpenEXR.File({"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION}, planes).write(str(path))


def test_exr_read_back_exactly(tmp_path):
    rng = np.random.default_rng(2)
    rgb = (rng.random((5, 7, 3)) * 4).astype(np.float32)        # HDR values above 1 are kept
    write_exr(tmp_path / "x.exr", {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2]})
    back = read_image(tmp_path / "x.exr")
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, rgb)


def test_exr_blender_dataset_is_linear_and_premultiplied(tmp_path):
    """EXR frames: color_space 'linear', values exact, RGBA treated as premultiplied: rgb + bg * (1 - a)."""
    root = copy_fixture("tiny_blender", tmp_path)
    rng = np.random.default_rng(3)
    written = {}
    for png in list(root.glob("*/r_*.png")):
        a = rng.random((16, 24)).astype(np.float32)
        rgb = (rng.random((16, 24, 3)) * a[..., None]).astype(np.float32)   # premultiplied
        write_exr(png.with_suffix(".exr"), {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": a})
        written[png.with_suffix(".exr").relative_to(root).as_posix()] = (rgb, a)
        png.unlink()
    ds = load_dataset(root, background=(1.0, 0.5, 0.0))
    assert ds.color_space == "linear"
    for v in ds.views:
        rgb, a = written[v.name]
        np.testing.assert_allclose(v.load_image(), rgb + np.array([1.0, 0.5, 0.0], np.float32) * (1 - a[..., None]),
                                   atol=1e-6)


# ------------------------------------------------------------------------------------------------ errors
def test_error_empty_and_unknown_folders(tmp_path):
    with pytest.raises(ValueError, match=r"empty folder"):
        load_dataset(tmp_path)
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(ValueError, match=r"unknown dataset layout"):
        detect_layout(tmp_path)
    with pytest.raises(ValueError, match=r"nothere: dataset folder not found"):
        load_dataset(tmp_path / "nothere")


def one_line(excinfo) -> str:
    msg = str(excinfo.value)
    assert "\n" not in msg, msg
    return msg


def test_error_colmap_missing_image(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    (root / "images" / "b.png").unlink()
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{root / 'images' / 'b.png'}: image file not found")


def test_error_colmap_image_size(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    Image.new("RGB", (20, 16)).save(root / "images" / "c.png")
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{root / 'images' / 'c.png'}: image is 20x16, but ")


def test_error_colmap_unsupported_model(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    (root / "sparse" / "0" / "cameras.txt").write_text("1 OPENCV_FISHEYE 24 16 20 20 11.5 7.25 0.1 0 0 0\n")
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{root / 'sparse' / '0' / 'cameras.txt'}, line 1: unsupported COLMAP camera "
                                  "model OPENCV_FISHEYE")


def test_error_colmap_malformed_model(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    (root / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 24 16 20\n")
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e) == f"{root / 'sparse' / '0' / 'cameras.txt'}, line 1: a PINHOLE camera has 4 parameters, got 1"
    (root / "sparse" / "0" / "points3D.txt").unlink()
    with pytest.raises(ValueError, match=r"incomplete COLMAP model, missing points3D\.txt"):
        load_dataset(root)


def _edit_lines(path: Path, edit) -> None:
    lines = path.read_text().splitlines()
    path.write_text("".join(line + "\n" for line in edit(lines)))


# (file, edit of its lines, expected message after "<file>, line N: "); line 3 of images.txt is the first image's
# header (after two comment lines), line 4 its points; line 2 of points3D.txt is the first point.
_MALFORMED_TEXT = [
    ("images", lambda L: L[:2] + [L[2].rsplit(" ", 1)[0]] + L[3:], 3,
     "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (10 fields, names without spaces), got 9 fields"),
    ("images", lambda L: L[:2] + [L[2].replace(" ", " abc", 1)] + L[3:], 3, "QW is 'abc0.40193708680852441', not a number"),
    ("images", lambda L: L[:3] + [L[3] + " 1.0"] + L[4:], 4, "the points of image 'a.png' are not X Y POINT3D_ID triples"),
    ("images", lambda L: L[:3] + L[4:], 4, "the points of image 'a.png' are not X Y POINT3D_ID triples (10 values)"),
    ("images", lambda L: L[:3], 4, "the file ends before the points line of image 'a.png'"),
    ("images", lambda L: L[:2] + [L[2].replace(" 1 a.png", " 7 a.png")] + L[3:], 3,
     "image 'a.png' refers to camera 7, which cameras does not define (cameras: 1)"),
    ("images", lambda L: L[:2] + [L[2]] * 2 + L[3:], 4, "the points of image 'a.png' are not X Y POINT3D_ID triples"),
    ("images", lambda L: L[:4] + L[2:4] + L[4:], 5, "duplicate IMAGE_ID 1"),
    ("cameras", lambda L: [L[0], L[1].replace("PINHOLE", "FOO")], 2, "unsupported COLMAP camera model FOO (camera 1)"),
    ("cameras", lambda L: [L[0], L[1].replace(" 24 ", " -24 ")], 2, "camera 1 has the image size -24x16"),
    ("cameras", lambda L: [L[0], L[1].replace(" 20.0 ", " nan ", 1)], 2, "camera 1 has non-finite parameters"),
    ("cameras", lambda L: [L[0], L[1], L[1]], 3, "duplicate CAMERA_ID 1"),
    ("points3D", lambda L: [L[0], L[1].replace(" ", " x", 1)] + L[2:], 2, "X is 'x0.10956934985716349', not a number"),
    ("points3D", lambda L: [L[0], L[1] + " 3"] + L[2:], 2,
     "expected POINT3D_ID X Y Z R G B ERROR and IMAGE_ID POINT2D_IDX pairs, got 15 fields"),
    ("points3D", lambda L: [L[0], L[1].replace(" 20 76 ", " 20 760 ")] + L[2:], 2, "colour [20, 760, 123] is outside 0..255"),
]


@pytest.mark.parametrize("stem, edit, line, message", _MALFORMED_TEXT)
def test_error_colmap_malformed_text_names_file_and_line(tmp_path, stem, edit, line, message):
    """A malformed COLMAP text model is refused with the file, the line and the problem (pycolmap said only
    "Check failed: line_stream1 >> ..." or "Rig with ID 7 does not exist")."""
    root = copy_fixture("tiny_colmap", tmp_path)
    path = root / "sparse" / "0" / f"{stem}.txt"
    _edit_lines(path, edit)
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{path}, line {line}: {message}")


def test_error_colmap_non_utf8_text(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    path = root / "sparse" / "0" / "images.txt"
    path.write_bytes(path.read_bytes()[:200] + b"\xff\xfe")
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e) == f"{path}, line 3: not UTF-8 text"


def test_error_colmap_malformed_binary(tmp_path):
    """A malformed binary model names the file, the record and the byte offset."""
    import pycolmap

    root = copy_fixture("tiny_colmap", tmp_path)
    sparse = root / "sparse" / "0"
    pycolmap.Reconstruction(str(sparse)).write_binary(str(sparse))
    for stem in ("cameras", "images", "points3D"):
        (sparse / f"{stem}.txt").unlink()
    assert len(load_dataset(root, test_every=0).train) == 3
    images = sparse / "images.bin"
    good = images.read_bytes()
    cases = [
        (good[:250], f"{images}: truncated file (image record 1, byte 230 of 250)"),
        (good[:400], f"{images}: 6 2D points do not fit in the rest of the file (image record 1, byte 308 of 400)"),
        (good + b"\0", f"{images}: 1 bytes after the last record (byte {len(good)} of {len(good) + 1})"),
        (struct.pack("<Q", 10**12) + good[8:], f"{images}: 1000000000000 images do not fit in the file (byte 8 of "),
    ]
    for data, message in cases:
        images.write_bytes(data)
        with pytest.raises(ValueError) as e:
            load_dataset(root)
        assert one_line(e).startswith(message), one_line(e)
    images.write_bytes(good)
    cameras = sparse / "cameras.bin"
    data = bytearray(cameras.read_bytes())
    data[12:16] = struct.pack("<i", 5)         # OPENCV_FISHEYE
    cameras.write_bytes(bytes(data))
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{cameras}: unsupported COLMAP camera model id 5 = OPENCV_FISHEYE (camera 1); "
                                  "supported: 0 SIMPLE_PINHOLE") and one_line(e).endswith("(camera record 0, byte 32 of 64)")


def test_error_blender_malformed_json(tmp_path):
    root = copy_fixture("tiny_blender", tmp_path)
    p = root / "transforms_train.json"
    p.write_text(p.read_text()[:-10])
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{p}: malformed JSON")


def test_error_blender_missing_image_and_size(tmp_path):
    root = copy_fixture("tiny_blender", tmp_path)
    (root / "test" / "r_0.png").unlink()
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{root / 'test' / 'r_0.png'}: image file not found")
    Image.new("RGBA", (24, 17)).save(root / "test" / "r_0.png")
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e).startswith(f"{root / 'test' / 'r_0.png'}: image is 24x17, but {root / 'transforms_test.json'}")


def test_error_blender_nan_pose_and_missing_fields(tmp_path):
    root = copy_fixture("tiny_blender", tmp_path)
    p = root / "transforms_train.json"
    d = json.loads(p.read_text())
    d["frames"][1]["transform_matrix"][0][3] = float("nan")
    p.write_text(json.dumps(d))               # json.dumps writes NaN, which json.load accepts
    with pytest.raises(ValueError) as e:
        load_dataset(root)
    assert one_line(e) == f"{p}: frame 1 (./train/r_1): transform_matrix has non-finite entries (NaN/inf)"
    d["frames"][1]["transform_matrix"] = (np.diag([2.0, 2.0, 2.0, 1.0])).tolist()
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"frame 1 \(\./train/r_1\): transform_matrix is not a rigid"):
        load_dataset(root)
    d["frames"][1]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"frame 1 \(\./train/r_1\): transform_matrix must be 4x4"):
        load_dataset(root)
    p.write_text(json.dumps({"frames": []}))
    with pytest.raises(ValueError, match=r"transforms_train\.json: no 'frames' list"):
        load_dataset(root)
    d = json.loads((root / "transforms_test.json").read_text())
    for k in ("camera_angle_x", "fl_x"):
        d.pop(k)
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"transforms_train\.json: frame 0 \(\./test/r_0\): no focal length"):
        load_dataset(root)


def test_error_ngp_fisheye_and_all_missing(tmp_path):
    root = copy_fixture("tiny_ngp", tmp_path)
    p = root / "transforms.json"
    d = json.loads(p.read_text())
    p.write_text(json.dumps({**d, "camera_model": "OPENCV_FISHEYE"}))
    with pytest.raises(ValueError, match=r"transforms\.json: frame 0 \(images/0000\.png\): unsupported camera model"):
        load_dataset(root)
    p.write_text(json.dumps(d))
    shutil.rmtree(root / "images")
    with pytest.raises(ValueError, match=r"transforms\.json: none of the 5 frames has its image file"):
        load_dataset(root)


@pytest.mark.parametrize("kwargs, message", [
    (dict(resolution=0), "resolution must be a positive integer"),
    (dict(resolution=1.5), "resolution must be a positive integer"),
    (dict(test_every=-1), "test_every must be an integer >= 0"),
    (dict(background=(1, 1)), "background must be three numbers"),
])
def test_error_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        load_dataset(DATA / "tiny_colmap", **kwargs)


def test_loading_writes_nothing(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    ds = load_dataset(root, resolution=2)
    for v in ds.views:
        v.load_image()
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before


def test_colmap_without_points_gets_random_points(tmp_path):
    root = copy_fixture("tiny_colmap", tmp_path)
    model = root / "sparse" / "0"
    lines = (model / "images.txt").read_text().splitlines()
    header = [l for l in lines if l.startswith("#")]
    body = [l for l in lines if not l.startswith("#")]
    (model / "images.txt").write_text("\n".join(header + [x for pose in body[0::2] for x in (pose, "")]) + "\n")
    (model / "points3D.txt").write_text("# no points\n")
    ds = load_dataset(root, random_points=500)
    assert ds.points_from == "cube"                 # (a run says which points it starts from: runs.initial_points)
    assert ds.points_xyz.shape == (500, 3) and ds.points_rgb.shape == (500, 3)


def test_dataset_pickles(tmp_path):
    """Views (with their undistorters) survive pickling, e.g. to worker processes."""
    import pickle

    ds = load_dataset(DATA / "tiny_ngp")
    ds.train[0].load_image()                        # fills the grid cache, which is not pickled
    back = pickle.loads(pickle.dumps(ds))
    np.testing.assert_array_equal(back.train[0].load_image(), ds.train[0].load_image())
    assert back.extent == ds.extent


def test_fingerprint_follows_content_and_lens(tmp_path):
    """The resume fingerprint is stable across loads and changes with an image's bytes and with the lens distortion
    alone (the undistorted pinhole intrinsics can stay the same when only k1 changes)."""
    from mi_gaussians.data.dataset import fingerprint

    root = copy_fixture("tiny_ngp", tmp_path)
    first = fingerprint(load_dataset(root))
    assert fingerprint(load_dataset(root)) == first
    meta = json.loads((root / "transforms.json").read_text())
    meta["k1"] = meta["k1"] + 1e-3
    (root / "transforms.json").write_text(json.dumps(meta))
    lens = fingerprint(load_dataset(root))
    assert lens != first
    img = sorted((root / "images").iterdir())[0]
    Image.open(img).transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(img)
    assert fingerprint(load_dataset(root)) not in (first, lens)


def test_fingerprint_is_canonical():
    """The point order (file order now, pycolmap's hash order before) and last-bit differences of a pose (another
    parser's arithmetic) do not change the fingerprint; a moved point does."""
    import dataclasses

    from mi_gaussians.data.dataset import FINGERPRINT_VERSION, fingerprint

    ds = load_dataset(DATA / "tiny_colmap")
    first = fingerprint(ds)
    assert first.startswith(FINGERPRINT_VERSION + ":")
    perm = np.random.default_rng(0).permutation(len(ds.points_xyz))
    assert fingerprint(dataclasses.replace(ds, points_xyz=ds.points_xyz[perm], points_rgb=ds.points_rgb[perm])) == first
    v = ds.train[0]
    nudged = dataclasses.replace(v.camera, world_to_camera=v.camera.world_to_camera + 6.7e-16)
    assert fingerprint(dataclasses.replace(ds, train=[dataclasses.replace(v, camera=nudged)] + ds.train[1:])) == first
    moved = ds.points_xyz.copy()
    moved[0, 0] += 1e-3
    assert fingerprint(dataclasses.replace(ds, points_xyz=moved)) != first
