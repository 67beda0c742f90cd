"""Initialization of Gaussians from points: kNN scales, colours, defaults, degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest

import mitsuba as mi

from mi_gaussians.conventions import SH_C0
from mi_gaussians.model.gaussians import Gaussians
from mi_gaussians.model.init import MIN_DIST2, init_from_points, mean_knn_dist2

KEYS = ("means", "scales", "rotations", "opacities", "sh_dc", "sh_rest")


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    mi.set_variant(variant)     # (test_plugins switches variants: start each module on the run's own)


def brute_force_scales(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """log(sqrt(max(mean of the k smallest squared distances to OTHER points, 1e-7))), float64 (N,)."""
    xyz = xyz.astype(np.float64)
    n = xyz.shape[0]
    d2 = ((xyz[:, None, :] - xyz[None, :, :]) ** 2).sum(-1)
    d2[np.arange(n), np.arange(n)] = np.inf  # exclude the point itself (not its duplicates)
    kk = min(k, n - 1)
    if kk == 0:
        return np.full(n, 0.5 * np.log(1e-7))
    near = np.sort(d2, axis=1)[:, :kk]
    return 0.5 * np.log(np.maximum(near.mean(axis=1), 1e-7))


def test_scales_match_brute_force_knn():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(300, 3)) * [1.0, 2.0, 0.5]
    out = init_from_points(xyz, rng.random((300, 3)))
    expect = brute_force_scales(xyz)
    assert out["scales"].shape == (300, 3) and out["scales"].dtype == np.float32
    assert np.all(out["scales"] == out["scales"][:, :1])  # isotropic
    np.testing.assert_allclose(out["scales"][:, 0], expect, rtol=1e-6, atol=1e-6)


def test_duplicate_points():
    rng = np.random.default_rng(1)
    base = rng.normal(size=(20, 3))
    xyz = np.concatenate([base, base[:5], base[:1], base[:1], base[:1]])  # point 0 appears 5 times
    out = init_from_points(xyz, np.full((xyz.shape[0], 3), 0.5))
    np.testing.assert_allclose(out["scales"][:, 0], brute_force_scales(xyz), rtol=1e-6, atol=1e-6)
    floor = 0.5 * np.log(MIN_DIST2)
    for i in (0, 20, 25, 26, 27):  # >= 3 exact duplicates: all 3 neighbours at distance 0 -> floor
        np.testing.assert_allclose(out["scales"][i], floor, rtol=1e-6)
    # a point with one duplicate: mean over (0, d2, d3)
    assert np.all(out["scales"][1] > floor)
    assert np.all(np.isfinite(out["scales"]))


def test_all_points_identical():
    out = init_from_points(np.ones((6, 3)), np.zeros((6, 3)))
    np.testing.assert_allclose(out["scales"], 0.5 * np.log(MIN_DIST2), rtol=1e-6)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_few_points(n):
    xyz = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])[:n]
    out = init_from_points(xyz, np.full((n, 3), 0.25), sh_degree=1)
    assert all(out[k].shape[0] == n for k in KEYS)
    np.testing.assert_allclose(out["scales"][:, 0], brute_force_scales(xyz), rtol=1e-6)
    if n == 1:
        np.testing.assert_allclose(out["scales"], 0.5 * np.log(MIN_DIST2), rtol=1e-6)
    if n == 2:
        np.testing.assert_allclose(out["scales"], np.log(3.0), rtol=1e-6)  # one neighbour at distance 3
    if n == 3:
        # point 0: neighbours at 3 and 4 -> mean d2 = 12.5; point 1: 3 and 5 -> 17; point 2: 4 and 5 -> 20.5
        np.testing.assert_allclose(out["scales"][:, 0], 0.5 * np.log([12.5, 17.0, 20.5]), rtol=1e-6)
    assert np.array_equal(mean_knn_dist2(xyz[:1]), [0.0])


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_other_parameters(degree):
    rng = np.random.default_rng(degree)
    xyz = rng.normal(size=(10, 3)).astype(np.float32)
    rgb = rng.random((10, 3))
    out = init_from_points(xyz, rgb, sh_degree=degree)
    assert set(out) == set(KEYS)
    assert all(v.dtype == np.float32 and v.flags.c_contiguous for v in out.values())
    assert np.array_equal(out["means"], xyz)
    assert np.array_equal(out["rotations"], np.tile([1.0, 0.0, 0.0, 0.0], (10, 1)))
    np.testing.assert_allclose(out["opacities"], np.log(0.1 / 0.9), rtol=1e-7)
    np.testing.assert_allclose(out["sh_dc"], (rgb - 0.5) / SH_C0, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(out["sh_dc"] * SH_C0 + 0.5, rgb, atol=1e-6)
    assert out["sh_rest"].shape == (10, (degree + 1) ** 2 - 1, 3) and not out["sh_rest"].any()
    g = Gaussians.from_points(xyz, rgb, sh_degree=degree)
    assert g.sh_degree == degree and g.n == 10


def test_uint8_colours_and_custom_opacity():
    rgb = np.array([[0, 128, 255], [255, 255, 255]], np.uint8)
    out = init_from_points(np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]], rgb, initial_opacity=0.5)
    np.testing.assert_allclose(out["sh_dc"], (rgb / 255.0 - 0.5) / SH_C0, rtol=1e-6, atol=1e-7)
    assert np.all(out["opacities"] == 0.0)


@pytest.mark.parametrize("kwargs,match", [
    ({"xyz": np.zeros((0, 3)), "rgb": np.zeros((0, 3))}, "empty"),
    ({"xyz": np.zeros((4, 2)), "rgb": np.zeros((4, 3))}, "shape"),
    ({"xyz": np.zeros((4, 3)), "rgb": np.zeros((3, 3))}, "colours"),
    ({"xyz": np.array([[0, 0, np.nan]] * 2), "rgb": np.zeros((2, 3))}, "non-finite"),
    ({"xyz": np.zeros((2, 3)), "rgb": np.zeros((2, 3)), "sh_degree": 4}, "sh_degree"),
    ({"xyz": np.zeros((2, 3)), "rgb": np.zeros((2, 3)), "initial_opacity": 1.0}, "initial_opacity"),
])
def test_invalid_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        init_from_points(**kwargs)



def test_frustum_sampler_samples_where_the_cameras_look():
    """points_in_view: every point is in front of and inside at least one camera; a ring of inward-looking cameras
    gets its points where the views overlap (near the centre), not spread through each whole frustum; seeded."""
    from mi_gaussians.data.camera import Camera
    from mi_gaussians.data.pointcloud import camera_extent, points_in_view

    cams = []
    for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        c = np.array([4 * np.cos(a), 0.5 * np.sin(3 * a), 4 * np.sin(a)])
        fwd = -c / np.linalg.norm(c)
        right = np.cross(fwd, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ c
        cams.append(Camera(width=64, height=48, fx=60.0, fy=60.0, cx=32.0, cy=24.0, world_to_camera=w2c))
    xyz, rgb = points_in_view(4000, cams, seed=1)
    assert xyz.shape == (4000, 3) and rgb.shape == (4000, 3) and np.all((rgb >= 0) & (rgb < 1))
    seen = np.zeros(len(xyz), int)
    for c in cams:
        uv, z = c.project(xyz.astype(np.float64))
        seen += (z > 0.2) & (uv[:, 0] >= 0) & (uv[:, 0] < 64) & (uv[:, 1] >= 0) & (uv[:, 1] < 48)
    assert np.all(seen >= 1)
    # concentrated where the cameras overlap: far more points near the centre than uniform candidates have
    mean, extent = camera_extent(np.stack([c.center for c in cams]))
    r = np.linalg.norm(xyz - mean, axis=1)
    uniform, _ = points_in_view(4000, cams[:1], seed=1)           # one camera: no overlap to favour
    assert np.median(r) < 0.7 * np.median(np.linalg.norm(uniform - mean, axis=1))
    assert np.mean(seen) > 3
    np.testing.assert_array_equal(points_in_view(4000, cams, seed=1)[0], xyz)


def test_random_init_setting(tmp_path):
    import mi_gaussians as mig
    from synthetic_dataset import make_blender_dataset

    scene = make_blender_dataset(tmp_path / "scene")
    cube = mig.load_dataset(scene, random_points=3000)
    frustum = mig.load_dataset(scene, random_points=3000, random_init="frustum")
    assert np.abs(cube.points_xyz).max() <= 1.3 and len(frustum.points_xyz) == 3000
    assert not np.array_equal(cube.points_xyz, frustum.points_xyz)
    with pytest.raises(ValueError, match="random_init"):
        mig.load_dataset(scene, random_init="sphere")


def _look_at(center, target, up=(0.0, 0.0, 1.0), size=(64, 48), f=60.0):
    from mi_gaussians.data.camera import Camera

    c = np.asarray(center, float)
    fwd = np.asarray(target, float) - c
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ c
    return Camera(width=size[0], height=size[1], fx=f, fy=f, cx=size[0] / 2, cy=size[1] / 2, world_to_camera=w2c)


def _rigs(scale=1.0):
    """An orbit of 16 cameras at radius 4 around points near the origin, and a forward-facing rig of 12 cameras on a
    disk of radius 0.3 looking 5 units down at a wall of points (a room, an LLFF capture); everything times scale."""
    rng = np.random.default_rng(3)
    orbit = [_look_at(scale * np.array([4 * np.cos(a), 4 * np.sin(a), 1.0 + 0.5 * np.sin(2 * a)]), (0, 0, 0))
             for a in np.linspace(0, 2 * np.pi, 16, endpoint=False)]
    blob = scale * rng.normal(0, 0.5, (3000, 3))
    disk = [_look_at(scale * np.array([0.3 * np.cos(a), 0.3 * np.sin(a), 0.0]),
                     scale * np.array([0.3 * np.cos(a), 0.3 * np.sin(a), 0.0]) + scale * np.array([0, 0, 5.0]),
                     up=(0.0, 1.0, 0.0)) for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    wall = scale * np.concatenate([rng.uniform(-4, 4, (3000, 2)), np.full((3000, 1), 5.0)], axis=1)
    return (orbit, blob), (disk, wall)


def test_scene_extent_is_the_rigs_around_an_object_and_the_seen_depth_in_front_of_a_wall():
    """data.extent: around an object the cameras' spread is the larger scale and both rules give the reference's
    extent exactly; a forward-facing rig standing close together and looking 5 units away measures 5 by the depth it
    sees, where its spread alone says 0.33; with no points, or none any camera sees, the spread; lengths scale with
    the world."""
    from mi_gaussians.data.pointcloud import camera_extent, scene_extent, seen_depth

    (orbit, blob), (disk, wall) = _rigs()
    spread_orbit = camera_extent(np.stack([c.center for c in orbit]))[1]
    assert scene_extent(orbit, blob, "scene") == scene_extent(orbit, blob, "cameras") == spread_orbit
    assert 3.5 < seen_depth(orbit, blob) < spread_orbit
    spread_disk = camera_extent(np.stack([c.center for c in disk]))[1]
    assert spread_disk == pytest.approx(0.33)
    assert scene_extent(disk, wall, "cameras") == spread_disk
    assert scene_extent(disk, wall, "scene") == pytest.approx(5.0)
    behind = wall * np.array([1.0, 1.0, -1.0])                     # the same wall behind the cameras: not seen
    assert seen_depth(disk, behind) is None
    assert scene_extent(disk, behind) == scene_extent(disk, None) == spread_disk
    # 'depth': the seen depth alone, around the object too; the spread when nothing is seen
    assert scene_extent(orbit, blob, "depth") == seen_depth(orbit, blob)
    assert scene_extent(disk, wall, "depth") == pytest.approx(5.0)
    assert scene_extent(disk, behind, "depth") == scene_extent(disk, None, "depth") == spread_disk
    assert scene_extent(orbit, blob) == seen_depth(orbit, blob)      # the default rule: DataConfig's, 'depth'
    (orbit7, blob7), (disk7, wall7) = _rigs(scale=7.0)
    for rule in ("scene", "cameras", "depth"):
        assert scene_extent(orbit7, blob7, rule) == pytest.approx(7.0 * scene_extent(orbit, blob, rule))
        assert scene_extent(disk7, wall7, rule) == pytest.approx(7.0 * scene_extent(disk, wall, rule))
    with pytest.raises(ValueError, match="unknown rule 'rig'"):
        scene_extent(disk, wall, "rig")


def test_the_seen_depth_does_not_depend_on_the_rigs_shape():
    """A ring of cameras and a cap of cameras above, all 4 units from the same points: their spreads differ by a
    third (the cap's centre is raised towards its cameras), the depth they see the points at does not."""
    from mi_gaussians.data.pointcloud import camera_extent, scene_extent

    (_, blob), _ = _rigs()
    ring = [_look_at(4 * np.array([np.cos(a), np.sin(a), 0.0]), (0, 0, 0))
            for a in np.linspace(0, 2 * np.pi, 16, endpoint=False)]
    cap = [_look_at(4 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)]), (0, 0, 0))
           for a in np.linspace(0, 2 * np.pi, 8, endpoint=False) for e in (0.8, 1.0, 1.2)]
    spreads = [camera_extent(np.stack([c.center for c in rig]))[1] for rig in (ring, cap)]
    assert spreads[0] == pytest.approx(4.4) and spreads[1] < 0.75 * spreads[0]
    assert scene_extent(cap, blob, "depth") == pytest.approx(scene_extent(ring, blob, "depth"), rel=0.02)
    assert scene_extent(ring, blob, "depth") == pytest.approx(4.0, rel=0.05)   # (the median point: the centre)


def test_seen_depth_strides_a_large_point_set():
    """seen_depth over at most max_points evenly strided points: the same median as over all of them, to a small
    fraction, for a point set 10x the cap (and NaN rows ignored)."""
    from mi_gaussians.data.pointcloud import seen_depth

    _, (disk, _) = _rigs()
    rng = np.random.default_rng(5)
    wall = np.concatenate([rng.uniform(-4, 4, (20_000, 2)), rng.uniform(3, 9, (20_000, 1))], axis=1)
    wall[::97] = np.nan
    full = seen_depth(disk, wall, max_points=0)
    assert seen_depth(disk, wall, max_points=2000) == pytest.approx(full, rel=0.03)
    assert 6.0 < full < 8.0       # (the frustum widens with depth: more of the far points are seen)
