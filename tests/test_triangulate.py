"""Initial points triangulated from known poses (``data.init``, ``mi_gaussians.data.triangulate``): on a textured
sphere rendered by Mitsuba (known geometry) the points lie on its surface; the cache is reused; 'auto' takes a
layout's own points, else triangulates (adding the random points when the images have alpha), else falls back to
the cube saying why; the errors (one image, one shared centre, no texture); the pairs chosen from the poses;
``mi-gs points`` and the viewer's point clouds."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

import mi_gaussians as mig
from mi_gaussians.config import TrainConfig, TriangulateConfig
from mi_gaussians.data.triangulate import check_cameras, choose_pairs
from mi_gaussians.runs import training_dataset
from synthetic_dataset import look_at_c2w_gl
from test_cli import assert_one_line_error, run

RADIUS = 1.0


def _noise(h: int, w: int, seed: int) -> np.ndarray:
    """Colour noise blurred at three scales (blobs and corners for SIFT at every scale), (h, w, 3) in [0, 1]."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    img = sum(s * gaussian_filter(rng.standard_normal((h, w, 3)), (s, s, 0), mode="wrap") for s in (1.5, 4.0, 10.0))
    return ((img - img.min()) / (img.max() - img.min())).astype(np.float32)


def make_sphere_dataset(root: Path, n_views: int = 14, size: int = 200, textured: bool = True) -> Path:
    """A Blender-layout dataset of an emissive (noise-free, view-independent) sphere of radius 1 at the origin, seen
    from a ring of cameras at two elevations, RGBA (the sky is empty: alpha marks the sphere)."""
    import mitsuba as mi
    from PIL import Image

    texture = _noise(512, 1024, 1) if textured else np.full((4, 8, 3), 0.6, np.float32)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                          "ball": {"type": "sphere", "radius": RADIUS, "emitter": {
                              "type": "area", "radiance": {"type": "bitmap", "bitmap": mi.Bitmap(texture),
                                                           "raw": True}},
                                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}}}})
    fov = math.radians(40.0)
    f = 0.5 * size / math.tan(fov / 2)
    root.mkdir(parents=True, exist_ok=True)
    for split, count, offset in (("train", n_views, 0.0), ("test", 2, 0.37)):
        (root / split).mkdir(exist_ok=True)
        frames = []
        for i in range(count):
            az = 2 * math.pi * (i + offset) / count
            el = math.radians(25.0 if i % 2 else -5.0)
            eye = 3.5 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            c2w = look_at_c2w_gl(eye)
            cam = mig.Camera.from_camera_to_world_gl(c2w, size, size, f, f, size / 2, size / 2)
            sensor = cam.to_mitsuba()
            sensor["film"] = {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgba",
                              "rfilter": {"type": "box"}}
            sensor["sampler"] = {"type": "independent", "sample_count": 16}
            rgba = np.array(mi.render(scene, sensor=mi.load_dict(sensor), seed=i), np.float64)
            a = np.clip(rgba[..., 3:4], 0, 1)
            straight = np.where(a > 1e-6, rgba[..., :3] / np.maximum(a, 1e-6), 0.0)
            out = np.concatenate([np.clip(straight, 0, 1) ** (1 / 2.2), a], axis=-1)
            Image.fromarray((out * 255 + 0.5).astype(np.uint8), "RGBA").save(root / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    return root


@pytest.fixture(scope="module")
def sphere(tmp_path_factory) -> Path:
    return make_sphere_dataset(tmp_path_factory.mktemp("sphere") / "data")


def _cfg(*settings) -> TrainConfig:
    return TrainConfig().with_settings(["data.background=0,0,0", *settings])


def test_triangulated_points_lie_on_the_sphere_and_the_cache_is_reused(sphere, tmp_path, monkeypatch):
    lines = []
    ds = training_dataset(sphere, _cfg("data.init=triangulate"), tmp_path / "run", log=lines.append)
    assert ds.points_from == "triangulated"
    r = np.linalg.norm(ds.points_xyz.astype(np.float64), axis=1)
    off = np.abs(r - RADIUS)
    # stated tolerance: 95 % of the points within 1 % of the radius of the true surface, the median within 0.3 %
    assert len(r) >= 300, len(r)
    assert np.percentile(off, 95) < 0.01 * RADIUS and np.median(off) < 0.003 * RADIUS, np.percentile(off, [50, 95])
    assert np.all((ds.points_rgb >= 0) & (ds.points_rgb <= 1)) and ds.points_rgb.std() > 0.05   # (coloured)
    assert [ln.split("]")[0] for ln in lines if ln.startswith("triangulation [")] == [
        "triangulation [1/4", "triangulation [2/4", "triangulation [3/4", "triangulation [4/4"]
    assert all(ln.rstrip().endswith(" s)") for ln in lines if ln.startswith("triangulation ["))   # (each timed)
    # a second run reuses the result: pycolmap is not called again
    import pycolmap

    monkeypatch.setattr(pycolmap, "extract_features", lambda *a, **k: pytest.fail("triangulated again"))
    again = []
    ds2 = training_dataset(sphere, _cfg("data.init=triangulate"), tmp_path / "run", log=again.append)
    assert np.array_equal(ds2.points_xyz, ds.points_xyz) and any("reused" in ln for ln in again)
    # a damaged cache (truncated, emptied, random bytes, wrong arrays) is computed again with one line, not a crash
    monkeypatch.undo()
    (cached,) = (tmp_path / "run" / "points").glob("*/points.npz")
    good = cached.read_bytes()
    rng = np.random.default_rng(0)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, xyz=np.zeros((5, 2)), rgb=np.zeros((5, 3)), seconds="{}", pairs=1, verified=1)
    for damaged in (good[: len(good) // 2], b"", rng.bytes(4096), wrong.read_bytes()):
        cached.write_bytes(damaged)
        lines = []
        ds3 = training_dataset(sphere, _cfg("data.init=triangulate"), tmp_path / "run", log=lines.append)
        said = [ln for ln in lines if "damaged" in ln]
        assert len(said) == 1 and said[0].startswith(f"note: {cached}: damaged cache of initial points"), lines
        assert said[0].endswith("computing them again") and "\n" not in said[0]
        assert ds3.points_from == "triangulated" and len(ds3.points_xyz) >= 300
        assert np.load(cached)["xyz"].shape == ds3.points_xyz.shape          # (written again, whole)
    monkeypatch.setattr(pycolmap, "extract_features", lambda *a, **k: pytest.fail("triangulated again"))
    # other settings: another cache entry
    with pytest.raises(pytest.fail.Exception, match="triangulated again"):
        training_dataset(sphere, _cfg("data.init=triangulate", "triangulate.min_angle=2"), tmp_path / "run",
                         log=None)


def test_auto_prefers_a_layouts_own_points_then_triangulation(sphere, tmp_path):
    colmap = Path(__file__).parent / "data" / "tiny_colmap"
    lines = []
    ds = training_dataset(colmap, _cfg(), tmp_path / "a", log=lines.append)
    assert ds.points_from == "layout" and lines == [f"initial points: the dataset's own {len(ds.points_xyz):,}"]
    # RGBA images (an object on an empty background): the triangulated points and the random ones (measured: README)
    lines.clear()
    ds = training_dataset(sphere, _cfg("data.random_points=500"), tmp_path / "b", log=lines.append)
    tri = training_dataset(sphere, _cfg("data.init=triangulate", "data.random_points=500"), tmp_path / "b",
                           log=None)
    cube = training_dataset(sphere, _cfg("data.init=cube", "data.random_points=500"), tmp_path / "b", log=None)
    assert tri.points_from == "triangulated" and ds.points_from == "triangulated+cube"
    np.testing.assert_array_equal(ds.points_xyz, np.concatenate([tri.points_xyz, cube.points_xyz]))
    np.testing.assert_array_equal(ds.points_rgb, np.concatenate([tri.points_rgb, cube.points_rgb]))
    (line,) = [ln for ln in lines if ln.startswith("initial points")]
    assert line == (f"initial points: {len(tri.points_xyz):,} triangulated from the 14 posed training images + the "
                     "500 random (cube), since the images have alpha (an object on an empty background)")
    # the same images without alpha (a scene that fills the views): the triangulated points alone
    from PIL import Image

    opaque = tmp_path / "opaque"
    shutil.copytree(sphere, opaque)
    for png in opaque.glob("*/*.png"):
        Image.open(png).convert("RGB").save(png)
    lines.clear()
    ds = training_dataset(opaque, _cfg("data.random_points=500"), tmp_path / "e", log=lines.append)
    assert ds.points_from == "triangulated" and len(ds.points_xyz) >= 100
    assert [ln for ln in lines if ln.startswith("initial points")] == [
        f"initial points: {len(ds.points_xyz):,} triangulated from the 14 posed training images"]
    with pytest.raises(ValueError, match="has no points of its own"):
        training_dataset(sphere, _cfg("data.init=points"), tmp_path / "c", log=None)
    ds = training_dataset(sphere, _cfg("data.init=cube", "data.random_points=1000"), tmp_path / "d", log=None)
    assert ds.points_from == "cube" and len(ds.points_xyz) == 1000


def test_textureless_images_fall_back_to_the_cube_saying_why(tmp_path):
    plain = make_sphere_dataset(tmp_path / "plain", n_views=6, size=96, textured=False)
    lines = []
    ds = training_dataset(plain, _cfg("data.random_points=2000"), tmp_path / "run", log=lines.append)
    assert ds.points_from == "cube" and len(ds.points_xyz) == 2000
    (line,) = [ln for ln in lines if ln.startswith("initial points")]
    assert line.startswith("initial points: 2,000 random in the cube, since no points could be triangulated (")
    assert "too little texture" in line or "fewer than triangulate.min_points" in line, line
    with pytest.raises(ValueError) as e:
        training_dataset(plain, _cfg("data.init=triangulate"), tmp_path / "run2", log=None)
    assert "\n" not in str(e.value) and str(plain) in str(e.value)


def test_cameras_without_baseline_or_alone_are_refused():
    cam = mig.Camera(64, 64, 50.0, 50.0, 32.0, 32.0, np.eye(4))
    with pytest.raises(ValueError, match="at least two training images"):
        check_cameras([cam], "ds")
    turned = np.eye(4)
    turned[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]                     # same centre, another direction
    with pytest.raises(ValueError, match="same centre .*no baseline"):
        check_cameras([cam, mig.Camera(64, 64, 50.0, 50.0, 32.0, 32.0, turned)], "ds")


def test_pairs_from_the_poses():
    def ring(n):
        cams = []
        for i in range(n):
            az = 2 * math.pi * i / n
            c2w = look_at_c2w_gl(3.0 * np.array([math.cos(az), math.sin(az), 0.3]))
            cams.append(mig.Camera.from_camera_to_world_gl(c2w, 64, 64, 50, 50, 32, 32))
        return cams

    assert choose_pairs(ring(5), 2, 30) == [(i, j) for i in range(5) for j in range(i + 1, 5)]   # (few: all)
    pairs = choose_pairs(ring(60), 4, 30)
    assert all((j - i) % 60 in (1, 2, 58, 59) for i, j in pairs)             # the nearest along the ring
    assert len(pairs) == 120                                                  # (4 each, shared: 60 * 4 / 2)


def test_points_command_and_viewing_a_point_cloud(sphere, tmp_path):
    out = tmp_path / "points.ply"
    r = run("points", sphere, "-o", out, "--init", "triangulate", "--background", "0", "--cache", tmp_path / "c",
            "--quiet")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    from mi_gaussians.cli.view import viewable_model
    from mi_gaussians.model.point_ply import is_point_cloud, read_points

    xyz, rgb = read_points(out)
    assert is_point_cloud(out) and summary == {"output": str(out), "points": len(xyz), "from": "triangulated"}
    ds = training_dataset(sphere, _cfg("data.init=triangulate"), tmp_path / "x", cache=str(tmp_path / "c"), log=None)
    np.testing.assert_allclose(xyz, ds.points_xyz, atol=0)                   # what a run would start from
    assert np.abs(rgb - ds.points_rgb).max() <= 0.5 / 255 + 1e-6
    g = viewable_model(out)                                                  # shown as small Gaussians
    assert g.n == len(xyz) and g.sh_degree == 0
    info = run("info", out)
    assert info.returncode == 0 and json.loads(info.stdout)["points"] == len(xyz)
    assert_one_line_error(run("points", sphere, "-o", out), "exists", "--overwrite")
    assert_one_line_error(run("points", sphere, "-o", sphere / "p.ply"), "lies in the dataset folder")
    assert_one_line_error(run("points", sphere, "-o", tmp_path / "p.ply", "--init", "shapes"),
                          "--init shapes: for a dataset folder")


def test_a_run_starts_from_the_triangulated_points(sphere, tmp_path):
    r = run("optimize", sphere, "-o", tmp_path / "run", "--iterations", 30, "--background", "0", "--eval-every", 0)
    assert r.returncode == 0, r.stderr                               # (not --quiet: the line below is information)
    assert "triangulated from the 14 posed training images" in r.stderr
    manifest = json.loads((tmp_path / "run" / ".mi-gs-manifest.json").read_text())["created"]
    assert "points" in manifest and list((tmp_path / "run" / "points").glob("*/points.npz"))
    # resuming does not triangulate again (the checkpoint holds the model), and the fingerprint agrees
    r = run("optimize", sphere, "-o", tmp_path / "run", "--resume", "--iterations", 35, "--quiet")
    assert r.returncode == 0 and "triangulat" not in r.stderr, r.stderr


def test_settings_are_checked():
    for bad, words in (("triangulate.neighbours=0", "must be >= 1"), ("triangulate.min_track_length=1", ">= 2"),
                       ("data.init=everywhere", "not one of auto, points")):
        with pytest.raises(ValueError, match=words):
            TrainConfig().with_settings([bad])
    assert TriangulateConfig().min_track_length == 2


def test_a_layouts_own_points_are_left_out_when_another_init_is_asked_for(tmp_path):
    """--init cube / frustum on a COLMAP layout start from random points, not its SfM ones; the run resumes (its
    fingerprint does not count points that are not the layout's)."""
    colmap = Path(__file__).parent / "data" / "tiny_colmap"
    own = training_dataset(colmap, _cfg(), tmp_path / "a", log=None)
    for init in ("cube", "frustum"):
        ds = training_dataset(colmap, _cfg(f"data.init={init}", "data.random_points=500"), tmp_path / init, log=None)
        assert ds.points_from == init and len(ds.points_xyz) == 500 != len(own.points_xyz)
    r = run("optimize", colmap, "-o", tmp_path / "run", "--iterations", 20, "--init", "frustum", "--eval-every", 0)
    assert r.returncode == 0 and "random (frustum)" in r.stderr, r.stderr        # (information: not --quiet)
    r = run("optimize", colmap, "-o", tmp_path / "run", "--resume", "--iterations", 25, "--quiet")
    assert r.returncode == 0, r.stderr


def test_a_points_cache_of_an_earlier_version_is_computed_again_and_called_so(tmp_path):
    """A cache our earlier version wrote (its arrays whole, a newer field missing: the SfM alignment's ``aligned_on``)
    is not called damaged: one note says it predates the change, and it is computed again."""
    from mi_gaussians.data.triangulate import load_cached_points

    cached = tmp_path / "points.npz"
    np.savez(cached, xyz=np.zeros((5, 3), np.float32), rgb=np.ones((5, 3), np.float32))
    lines = []
    assert load_cached_points(cached, ("aligned_on",), lines.append) is None
    assert lines == [f"note: {cached}: initial points computed by an earlier version (no aligned_on); computing "
                     "them again"]
    assert not cached.exists()
    np.savez(cached, xyz=np.zeros((5, 3), np.float32), rgb=np.ones((5, 3), np.float32), aligned_on=np.int64(4))
    assert int(load_cached_points(cached, ("aligned_on",), lines.append)["aligned_on"]) == 4 and len(lines) == 1
