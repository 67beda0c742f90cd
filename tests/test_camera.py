"""Camera record: JSON round trip, scaling, projection, conventions, and the Mitsuba sensor conversions (by rendering)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mi_gaussians.data.camera import Camera


def rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def make_camera(width=150, height=90, fx=120.0, fy=120.0, cx=60.3, cy=50.7, name="cam") -> Camera:
    w2c = np.eye(4)
    w2c[:3, :3] = rotation(0.2, -0.3, 0.1)
    w2c[:3, 3] = [0.1, -0.2, 3.0]
    return Camera(width, height, fx, fy, cx, cy, w2c, name)


def world_point(cam: Camera, p_cam) -> np.ndarray:
    """World point whose camera-space (OpenCV) coordinates are ``p_cam``."""
    return (cam.camera_to_world @ np.r_[np.asarray(p_cam, float), 1.0])[:3]


# ------------------------------------------------------------------------------------------------ JSON
def test_json_round_trip(tmp_path):
    cam = make_camera()
    cam.to_json(tmp_path / "cam.json")
    back = Camera.from_json(tmp_path / "cam.json")
    assert (back.width, back.height, back.fx, back.fy, back.cx, back.cy, back.name) == \
        (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.name)
    np.testing.assert_array_equal(back.world_to_camera, cam.world_to_camera)
    d = json.loads((tmp_path / "cam.json").read_text())
    assert len(d["world_to_camera"]) == 4 and len(d["world_to_camera"][0]) == 4


def test_json_errors_name_the_file(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(ValueError, match=r"bad\.json: malformed JSON"):
        Camera.from_json(p)
    p.write_text(json.dumps({"width": 10, "height": 10, "fx": 5}))
    with pytest.raises(ValueError, match=r"bad\.json: missing camera field"):
        Camera.from_json(p)
    with pytest.raises(ValueError, match=r"nothere\.json: camera file not found"):
        Camera.from_json(tmp_path / "nothere.json")
    p.write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"bad\.json: expected a JSON object"):
        Camera.from_json(p)


@pytest.mark.parametrize("kwargs, message", [
    (dict(width=0), "image size must be positive"),
    (dict(fx=-1.0), "focal lengths must be positive"),
    (dict(cx=float("nan")), "cx is not finite"),
])
def test_invalid_cameras(kwargs, message):
    args = dict(width=10, height=10, fx=5.0, fy=5.0, cx=5.0, cy=5.0, world_to_camera=np.eye(4))
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        Camera(**args)
    with pytest.raises(ValueError, match="non-finite"):
        Camera(10, 10, 5, 5, 5, 5, np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="4x4"):
        Camera(10, 10, 5, 5, 5, 5, np.eye(3))


# ------------------------------------------------------------------------------------------------ geometry
def test_project_and_center():
    cam = make_camera()
    p_cam = np.array([[0.4, -0.3, 3.0], [0.0, 0.0, 2.0]])
    pts = np.stack([world_point(cam, p) for p in p_cam])
    uv, z = cam.project(pts)
    np.testing.assert_allclose(z, p_cam[:, 2])
    np.testing.assert_allclose(uv, np.c_[cam.fx * p_cam[:, 0] / p_cam[:, 2] + cam.cx,
                                         cam.fy * p_cam[:, 1] / p_cam[:, 2] + cam.cy])
    # the centre projects nowhere: it is the point with camera coordinates 0
    np.testing.assert_allclose(cam.world_to_camera[:3, :3] @ cam.center + cam.world_to_camera[:3, 3], 0, atol=1e-12)


def test_scaled_keeps_pixel_geometry():
    """A resampled image sees the same point at the scaled pixel position (per axis, corner-aligned)."""
    cam = make_camera(width=151, height=91)
    small = cam.scaled(38, 23)
    assert (small.width, small.height) == (38, 23)
    pts = np.stack([world_point(cam, p) for p in [(0.4, -0.3, 3.0), (-0.7, 0.2, 4.0)]])
    uv, _ = cam.project(pts)
    uv_s, _ = small.project(pts)
    np.testing.assert_allclose(uv_s, uv * [38 / 151, 23 / 91], rtol=1e-12)
    np.testing.assert_array_equal(small.world_to_camera, cam.world_to_camera)


def test_from_camera_to_world_gl():
    """An OpenGL camera at (0, 0, 5) looking down -z (y up) sees the world origin at the principal point and world +y
    above it (smaller pixel row)."""
    c2w = np.eye(4)
    c2w[2, 3] = 5.0
    cam = Camera.from_camera_to_world_gl(c2w, 100, 80, 50.0, 50.0, 40.0, 30.0)
    uv, z = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(z, 5.0)
    np.testing.assert_allclose(uv[0], [40.0, 30.0])
    assert uv[1, 1] < 30.0 and uv[2, 0] > 40.0
    np.testing.assert_allclose(cam.center, [0, 0, 5])


# ------------------------------------------------------------------------------------------------ Mitsuba
def test_to_mitsuba_off_centre_principal_point_by_rendering(bright_sphere):
    """Non-square 150x90 image (not a multiple of 16) with cx, cy far from the centre: a small bright sphere renders
    where ``Camera.project`` puts it. A wrong sign of the principal-point offset would miss by 2 |c - W/2| ~ 29 px,
    a wrong axis flip by much more."""
    cam = make_camera(width=150, height=90, cx=60.3, cy=50.7)
    for p_cam in [(0.4, -0.3, 3.0), (-0.8, 0.5, 4.0), (0.0, 0.0, 3.0)]:
        p = world_point(cam, p_cam)
        img = bright_sphere.render(cam, p, radius=0.03)
        uv, _ = cam.project(p[None])
        np.testing.assert_allclose(bright_sphere.centroid(img), uv[0], atol=0.5)


def test_from_mitsuba_round_trip():
    import mitsuba as mi

    cam = make_camera(width=150, height=90, cx=60.3, cy=50.7)
    sensor = mi.load_dict(cam.to_mitsuba())
    back = Camera.from_mitsuba(sensor, name="back")
    assert (back.width, back.height) == (150, 90)
    np.testing.assert_allclose([back.fx, back.fy, back.cx, back.cy], [cam.fx, cam.fy, cam.cx, cam.cy], rtol=1e-6)
    np.testing.assert_allclose(back.world_to_camera, cam.world_to_camera, atol=1e-6)


@pytest.mark.parametrize("fov_axis", ["x", "y"])
def test_from_mitsuba_matches_look_at(fov_axis):
    """A Mitsuba ``look_at`` sensor converted with from_mitsuba sees its target at the image centre and the up vector
    towards smaller rows; the field of view is kept whichever axis it was given for."""
    import mitsuba as mi

    sensor = mi.load_dict({"type": "perspective", "fov": 40.0, "fov_axis": fov_axis,
                           "to_world": mi.ScalarTransform4f().look_at(origin=[1, 2, 3], target=[0, 0, 0.5],
                                                                      up=[0, 0, 1]),
                           "film": {"type": "hdrfilm", "width": 64, "height": 48}})
    cam = Camera.from_mitsuba(sensor)
    np.testing.assert_allclose(cam.center, [1, 2, 3], atol=1e-5)
    uv, z = cam.project(np.array([[0, 0, 0.5], [0, 0, 1.0]]))
    np.testing.assert_allclose(uv[0], [32.0, 24.0], atol=1e-4)
    assert z[0] > 0 and uv[1, 1] < 24.0
    np.testing.assert_allclose(math.degrees(cam.fov_x if fov_axis == "x" else cam.fov_y), 40.0, rtol=1e-5)


def test_to_mitsuba_refuses_non_square_pixels():
    cam = make_camera(fx=100.0, fy=120.0)
    with pytest.raises(ValueError, match="square pixels"):
        cam.to_mitsuba()


def test_focal_and_field_of_view_are_inverse():
    from mi_gaussians.data.camera import camera_center, focal_from_fov, fov_from_focal

    f = focal_from_fov(640, math.radians(60.0))
    assert abs(f - 320.0 / math.tan(math.radians(30.0))) < 1e-9
    assert abs(fov_from_focal(640, f) - math.radians(60.0)) < 1e-12
    w2c = np.eye(4)
    w2c[:3, 3] = [1.0, 2.0, 3.0]
    assert np.allclose(camera_center(w2c), [-1.0, -2.0, -3.0])
