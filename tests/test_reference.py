"""Self-tests of the NumPy reference renderer (tests/reference.py): closed forms, hand counts and independent checks.

Nothing here touches mi_gaussians.raster: the reference must be right on its own before the fast rasterizer is
compared against it.
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

import reference as ref  # noqa: E402
import scene_factory as sf  # noqa: E402

Camera = sf.Camera

C0 = ref.SH_C0
C1 = ref.SH_C1


def sigmoid(x):
    return 1.0 / (1.0 + math.exp(-x))


def one(mean, log_sigma=(-1.6, -1.6, -1.6), rot=(1.0, 0.0, 0.0, 0.0), logit=0.7, dc=(0.3, -0.4, 1.1), rest=None,
        degree=0):
    """float64 params of a single Gaussian."""
    k = (degree + 1) ** 2 - 1
    return {
        "means": np.array([mean], np.float64),
        "scales": np.array([log_sigma], np.float64),
        "rotations": np.array([rot], np.float64),
        "opacities": np.array([logit], np.float64),
        "sh_dc": np.array([dc], np.float64),
        "sh_rest": np.zeros((1, k, 3)) if rest is None else np.asarray(rest, np.float64).reshape(1, k, 3),
    }


def stack(*ps):
    return {k: np.concatenate([p[k] for p in ps]) for k in ps[0]}


def pixel_grid(cam):
    j, i = np.meshgrid(np.arange(cam.height), np.arange(cam.width), indexing="ij")
    return i + 0.5, j + 0.5


# ============================================================================================== one Gaussian, closed form
def test_single_isotropic_gaussian_matches_closed_form_everywhere():
    # camera at the origin looking down +z; odd width so that a pixel centre sits exactly on the projected mean
    cam = sf.identity_camera(33, 25, fx=40.0)  # cx = 16.5, cy = 12.5
    z, sigma, logit = 4.0, 0.2, 0.7
    dc = np.array([0.3, -0.4, 1.1])
    bg = np.array([0.1, 0.2, 0.3])
    p = one((0.0, 0.0, z), log_sigma=(math.log(sigma),) * 3, rot=(0.3, -0.2, 0.9, 0.1), logit=logit, dc=dc)
    out = ref.render_reference(p, cam, background=bg)

    o = sigmoid(logit)
    s2d = (40.0 / z) ** 2 * sigma**2 + 0.3  # isotropic EWA: (f / z)^2 sigma^2 + 0.3 = 4.3
    assert s2d == pytest.approx(4.3)
    X, Y = pixel_grid(cam)
    raw = o * np.exp(-0.5 * ((X - 16.5) ** 2 + (Y - 12.5) ** 2) / s2d)
    alpha = np.where(raw >= 1 / 255, np.minimum(0.99, raw), 0.0)
    colour = np.maximum(C0 * dc + 0.5, 0)
    np.testing.assert_allclose(out["alpha"], alpha, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out["rgb"], alpha[..., None] * colour + (1 - alpha[..., None]) * bg, rtol=1e-12)
    np.testing.assert_allclose(out["depth"], np.where(alpha > 0, z, 0.0), rtol=1e-12)
    # the centre pixel (16, 12) sits exactly on the mean: alpha = sigmoid(logit)
    assert out["alpha"][12, 16] == pytest.approx(o, rel=1e-15)
    # (18, 11): d = (-2, +1) -> alpha = o exp(-0.5 * 5 / 4.3)
    assert out["alpha"][11, 18] == pytest.approx(o * math.exp(-0.5 * 5 / 4.3), rel=1e-13)
    assert out["n_contrib"].max() == 1 and out["visible"].tolist() == [True]
    np.testing.assert_allclose(out["means2d"], [[16.5, 12.5]], atol=1e-14)
    np.testing.assert_allclose(out["cov2d"][0], np.diag([s2d, s2d]), rtol=1e-13, atol=1e-15)

    # near-one opacity: the centre clamps at 0.99
    out = ref.render_reference(one((0.0, 0.0, z), logit=10.0), cam)
    assert out["alpha"][12, 16] == 0.99


def test_alpha_threshold_region_is_the_closed_form_disc():
    cam = sf.identity_camera(33, 25, fx=40.0)
    z, sigma = 4.0, 0.8
    s2d = (40.0 / z) ** 2 * sigma**2 + 0.3  # 64.3
    X, Y = pixel_grid(cam)
    r2 = (X - 16.5) ** 2 + (Y - 12.5) ** 2
    # opacity 1.01 / 255: contributes exactly where r^2 / s2d <= 2 ln(1.01)
    out = ref.render_reference(one((0, 0, z), log_sigma=(math.log(sigma),) * 3, logit=sf.logit(1.01 / 255)), cam)
    inside = r2 / s2d <= 2 * math.log(1.01)
    assert inside.sum() == 5  # the centre pixel and its 4 neighbours (r^2 = 1 <= 1.2796 < 2)
    np.testing.assert_array_equal(out["n_contrib"] == 1, inside)
    # opacity 0.99 / 255: never reaches 1/255, never contributes, not visible
    out = ref.render_reference(one((0, 0, z), log_sigma=(math.log(sigma),) * 3, logit=sf.logit(0.99 / 255)), cam)
    assert out["alpha"].max() == 0 and not out["visible"][0] and out["n_contrib"].max() == 0
    out = ref.render_reference(one((0, 0, z), logit=-10.0), cam)
    assert out["alpha"].max() == 0 and not out["visible"][0]


# ============================================================================================== EWA covariance
def test_cov2d_on_axis_anisotropic_closed_form():
    cam = sf.identity_camera(32, 32, fx=40.0, fy=55.0)
    z, sx, sy, sz = 5.0, 0.3, 0.1, 0.7
    out = ref.render_reference(one((0, 0, z), log_sigma=np.log([sx, sy, sz])), cam)
    expect = np.diag([(40.0 / z) ** 2 * sx**2 + 0.3, (55.0 / z) ** 2 * sy**2 + 0.3])
    np.testing.assert_allclose(out["cov2d"][0], expect, rtol=1e-13, atol=1e-14)
    a, c = expect[0, 0], expect[1, 1]
    np.testing.assert_allclose(out["conics"][0], [1 / a, 0.0, 1 / c], rtol=1e-13, atol=1e-15)


def test_cov2d_off_axis_isotropic_closed_form():
    cam = sf.identity_camera(32, 32, fx=40.0)
    x, z, s = 1.0, 5.0, 0.3
    out = ref.render_reference(one((x, 0, z), log_sigma=(math.log(s),) * 3), cam)
    f = 40.0
    # J = [[f/z, 0, -f x / z^2], [0, f/z, 0]], Sigma = s^2 I
    a = (f / z) ** 2 * s**2 + (f * x / z**2) ** 2 * s**2 + 0.3
    c = (f / z) ** 2 * s**2 + 0.3
    np.testing.assert_allclose(out["cov2d"][0], [[a, 0], [0, c]], rtol=1e-13, atol=1e-14)


def _numeric_world_jacobian(cam: Camera, point, h=1e-6):
    """d pixel / d world point, by central differences of Camera.project (independent of the reference)."""
    J = np.zeros((2, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        J[:, k] = (cam.project(point + e)[0][0] - cam.project(point - e)[0][0]) / (2 * h)
    return J


def _scipy_rotation(q):
    from scipy.spatial.transform import Rotation

    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w]).as_matrix()  # scipy: (x, y, z, w), normalizes


def test_quaternion_to_matrix_matches_scipy():
    rng = np.random.default_rng(3)
    q = sf.random_quaternions(rng, 20, norm_range=(1e-3, 1e3))
    R = ref.quaternion_to_matrix(q)
    for qi, Ri in zip(q, R):
        np.testing.assert_allclose(Ri, _scipy_rotation(qi), atol=1e-13)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-13)
    with pytest.raises(ValueError, match="zero"):
        ref.quaternion_to_matrix(np.array([[0.0, 0.0, 0.0, 0.0]]))


def test_cov2d_generic_pose_equals_numeric_jacobian():
    # generic camera, random rotation: Sigma2D = Jw Sigma Jw^T + 0.3 I with Jw the numeric Jacobian of Camera.project
    cam = sf.generic_camera(48, 40, variant=1, fx=45.0, fy=50.0, cx=20.0, cy=23.0)
    rng = np.random.default_rng(7)
    for _ in range(5):
        mean = sf.pixel_to_world(cam, rng.uniform(0, 48), rng.uniform(0, 40), rng.uniform(1, 6))[0]
        ls = rng.normal(-1.5, 0.5, 3)
        q = sf.random_quaternions(rng, 1)[0]
        out = ref.render_reference(one(mean, log_sigma=ls, rot=q), cam)
        R = _scipy_rotation(q)
        Sigma = R @ np.diag(np.exp(2 * ls)) @ R.T
        Jw = _numeric_world_jacobian(cam, mean)
        np.testing.assert_allclose(out["cov2d"][0], Jw @ Sigma @ Jw.T + 0.3 * np.eye(2), rtol=1e-7)
        np.testing.assert_allclose(out["means2d"][0], cam.project(mean)[0][0], rtol=1e-13)
        assert not out["guard_clamped"].any()


def test_guard_band_clamps_the_jacobian_only():
    # a Gaussian projecting 2 W to the right of the image: J is evaluated at the guard-band edge u = (1.15 W - cx) / fx
    cam = sf.generic_camera(40, 30, variant=0, cx=13.0, cy=17.0)
    z = 3.0
    mean = sf.pixel_to_world(cam, 2.0 * 40, 10.0, z)[0]
    ls = np.log([2.0, 1.0, 1.5])
    q = (0.8, 0.1, -0.3, 0.2)
    out = ref.render_reference(one(mean, log_sigma=ls, rot=q), cam)
    assert out["guard_clamped"][0].tolist() == [True, False]
    np.testing.assert_allclose(out["means2d"][0], [80.0, 10.0], rtol=1e-12)  # mean2D is NOT clamped
    clamped_point = sf.pixel_to_world(cam, 1.15 * 40, 10.0, z)[0]  # same depth, same v, u at the guard edge
    R = _scipy_rotation(q)
    Sigma = R @ np.diag(np.exp(2 * ls)) @ R.T
    Jw = _numeric_world_jacobian(cam, clamped_point)
    np.testing.assert_allclose(out["cov2d"][0], Jw @ Sigma @ Jw.T + 0.3 * np.eye(2), rtol=1e-7)
    Jw_unclamped = _numeric_world_jacobian(cam, mean)
    assert not np.allclose(out["cov2d"][0], Jw_unclamped @ Sigma @ Jw_unclamped.T + 0.3 * np.eye(2), rtol=1e-3)
    # for a centred principal point, the guard band is the reference's 1.3 tan(fov / 2)
    cam_c = sf.generic_camera(40, 30)
    lim_x = (1.15 * 40 - cam_c.cx) / cam_c.fx
    assert lim_x == pytest.approx(1.3 * math.tan(cam_c.fov_x / 2), rel=1e-14)
    assert (-0.15 * 30 - cam_c.cy) / cam_c.fy == pytest.approx(-1.3 * math.tan(cam_c.fov_y / 2), rel=1e-14)


# ============================================================================================== compositing
def test_two_layers_composite_with_transmittance_products():
    cam = sf.identity_camera(33, 25, fx=40.0)
    bg = np.array([0.2, 0.5, 0.9])
    dc_far, dc_near = np.array([1.0, -0.5, 0.2]), np.array([-0.3, 0.8, 0.4])
    far = one((0.0, 0.0, 3.0), log_sigma=(math.log(0.3),) * 3, logit=1.2, dc=dc_far)
    near = one((0.05, -0.02, 2.0), log_sigma=(math.log(0.15),) * 3, logit=0.4, dc=dc_near)
    out = ref.render_reference(stack(far, near), cam, background=bg)  # the far one has the lower index
    X, Y = pixel_grid(cam)

    def alpha_of(mean, sigma, logit):
        x, y, z = mean
        J = np.array([[40.0 / z, 0, -40.0 * x / z**2], [0, 40.0 / z, -40.0 * y / z**2]])
        inv = np.linalg.inv(sigma**2 * J @ J.T + 0.3 * np.eye(2))  # isotropic Sigma = sigma^2 I
        dx, dy = 40.0 * x / z + 16.5 - X, 40.0 * y / z + 12.5 - Y
        raw = sigmoid(logit) * np.exp(-0.5 * (inv[0, 0] * dx * dx + 2 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy))
        return np.where(raw >= 1 / 255, np.minimum(0.99, raw), 0.0)

    a1 = alpha_of((0.05, -0.02, 2.0), 0.15, 0.4)  # near: first
    a2 = alpha_of((0.0, 0.0, 3.0), 0.3, 1.2)      # far: second
    c1, c2 = C0 * dc_near + 0.5, C0 * dc_far + 0.5
    T1, T2 = 1 - a1, (1 - a1) * (1 - a2)
    np.testing.assert_allclose(out["rgb"], a1[..., None] * c1 + (a2 * T1)[..., None] * c2 + T2[..., None] * bg,
                               rtol=1e-12)
    np.testing.assert_allclose(out["alpha"], 1 - T2, rtol=1e-12, atol=1e-15)
    acc = 1 - T2
    np.testing.assert_allclose(out["depth"], np.where(acc > 0, (2.0 * a1 + 3.0 * a2 * T1) / np.where(acc > 0, acc, 1),
                                                      0.0), rtol=1e-12)
    assert out["order"].tolist() == [1, 0]


def test_background_shows_through_where_nothing_is():
    bg = np.array([0.25, 0.5, 0.75])
    p, cam = sf.empty_scene()
    out = ref.render_reference(p, cam, background=bg)
    np.testing.assert_array_equal(out["rgb"], np.broadcast_to(bg, (cam.height, cam.width, 3)))
    assert out["alpha"].max() == 0 and out["depth"].max() == 0 and out["n_contrib"].max() == 0
    assert out["means2d"].shape == (0, 2) and out["visible"].shape == (0,)
    # a tiny Gaussian: every pixel it does not reach is exactly the background
    cam = sf.identity_camera(33, 25, fx=40.0)
    out = ref.render_reference(one((0, 0, 4.0), log_sigma=(-12.0,) * 3, logit=2.0), cam, background=bg)
    untouched = out["n_contrib"] == 0
    assert untouched.sum() == cam.width * cam.height - 9  # the 0.3 dilation reaches the 3 x 3 neighbourhood
    np.testing.assert_array_equal(out["rgb"][untouched], np.broadcast_to(bg, (untouched.sum(), 3)))
    np.testing.assert_array_equal(out["depth"][untouched], 0.0)


def _layer_stack(n, logit, z0=2.0, dz=0.01):
    """n Gaussians exactly on the optical axis (mean2D on the centre pixel), depths z0 + k dz, listed far to near."""
    rng = np.random.default_rng(1)
    ps = [one((0.0, 0.0, z0 + dz * k), log_sigma=(-1.0,) * 3, logit=logit, dc=rng.normal(0, 1, 3))
          for k in range(n)][::-1]
    return stack(*ps)


def test_early_termination_exact_count_half_opacity():
    # alpha = sigmoid(0) = 0.5 exactly at the centre pixel: T after k layers is 2^-k exactly; 2^-13 = 1.22e-4 >= 1e-4
    # but 2^-14 = 6.1e-5 < 1e-4, so 13 Gaussians contribute and the 14th stops the pixel (and does not contribute)
    cam = sf.identity_camera(33, 25, fx=40.0)
    p = _layer_stack(200, 0.0)
    for dtype in (np.float64, np.float32):
        out = ref.render_reference(p, cam, dtype=dtype)
        assert out["n_contrib"][12, 16] == 13
        assert out["final_T"][12, 16] == 2.0**-13
        assert out["alpha"][12, 16] == 1 - 2.0**-13
    out = ref.render_reference(p, cam)
    nearest_first = np.arange(200)[::-1]  # index 199 is the nearest
    colours = C0 * p["sh_dc"][nearest_first[:13]] + 0.5
    weights = 0.5 * 0.5 ** np.arange(13)
    np.testing.assert_allclose(out["rgb"][12, 16], np.maximum(colours, 0).T @ weights, rtol=1e-13)
    assert out["last_contrib"][12, 16] == nearest_first[12]
    # alpha = 0.3: (0.7)^k >= 1e-4 for k <= ln(1e-4) / ln(0.7) = 25.8 -> 25 contributors
    out = ref.render_reference(_layer_stack(200, sf.logit(0.3)), cam)
    assert out["n_contrib"][12, 16] == math.floor(math.log(1e-4) / math.log(0.7)) == 25
    assert out["final_T"][12, 16] == pytest.approx(0.7**25, rel=1e-12)
    # the final transmittance never drops below 1e-4 anywhere
    assert out["final_T"].min() >= 1e-4


def test_early_termination_opaque_layers_float64_vs_float32():
    # alpha = min(0.99, 0.99995) = 0.99. float64: (1 - 0.99)^2 = 1.0000000000000018e-4 >= 1e-4 -> 2 contributors.
    # float32: (1 - 0.99f)^2 = 9.99998e-5 < 1e-4 -> 1 contributor (the reference CUDA rasterizer's behaviour).
    cam = sf.identity_camera(33, 25, fx=40.0)
    p = _layer_stack(5, 10.0)
    out64 = ref.render_reference(p, cam)
    out32 = ref.render_reference(p, cam, dtype=np.float32)
    assert out64["n_contrib"][12, 16] == 2 and out32["n_contrib"][12, 16] == 1
    assert (1 - 0.99) ** 2 >= 1e-4 and np.float32(1 - np.float32(0.99)) ** 2 < np.float32(1e-4)
    # the pixel margin flags exactly this kind of pixel
    assert out64["pixel_margin"][12, 16] < 1e-12
    assert out64["rgb"].dtype == np.float64 and out32["rgb"].dtype == np.float32


def test_culling_at_the_near_plane():
    cam = sf.identity_camera(33, 25, fx=40.0)
    for z, culled in [(0.2, True), (0.2 * (1 + 1e-9), False), (0.21, False), (0.19, True), (0.0, True), (-1.0, True)]:
        out = ref.render_reference(one((0.0, 0.0, z), log_sigma=(-5.0,) * 3, logit=2.0), cam)
        assert out["culled"][0] == culled, z
        assert (out["alpha"].max() > 0) == (not culled), z
    # a big Gaussian whose mean is just behind the near plane but whose extent reaches far in front: culled
    out = ref.render_reference(one((0.0, 0.0, 0.1), log_sigma=(math.log(5.0),) * 3, logit=5.0), cam)
    assert out["culled"][0] and out["alpha"].max() == 0
    p, cam = sf.near_plane()
    out = ref.render_reference(p, cam)
    _, tz = cam.project(p["means"].astype(np.float64))
    np.testing.assert_array_equal(out["culled"], tz <= 0.2)
    assert (np.abs(tz - 0.2) > 4e-4).all()  # the scene keeps a margin (5e-4) from the threshold


# ============================================================================================== SH
def test_sh_degree0_colour_and_clamp():
    cam = sf.generic_camera(16, 12)
    dc = np.array([[0.3, -0.4, 1.1], [-3.0, 0.0, 5.0]])
    p = stack(one(sf.pixel_to_world(cam, 4, 6, 3.0)[0], dc=dc[0]), one(sf.pixel_to_world(cam, 12, 6, 3.0)[0], dc=dc[1]))
    out = ref.render_reference(p, cam)
    np.testing.assert_allclose(out["colors"], np.maximum(C0 * dc + 0.5, 0), rtol=1e-15)
    assert out["colors"][1, 0] == 0 and out["color_clamped"][1].tolist() == [True, False, False]
    assert out["colors"][1, 1] == 0.5


def test_sh_degree1_along_axes():
    rng = np.random.default_rng(5)
    dc = rng.normal(0, 1, (1, 3))
    rest = rng.normal(0, 1, (1, 3, 3))
    sh = np.concatenate([dc[:, None], rest], axis=1)[0]  # (4, 3)
    axes = {(1, 0, 0): -C1 * sh[3], (-1, 0, 0): C1 * sh[3], (0, 1, 0): -C1 * sh[1], (0, -1, 0): C1 * sh[1],
            (0, 0, 1): C1 * sh[2], (0, 0, -1): -C1 * sh[2]}
    for d, term in axes.items():
        c = ref.sh_to_color(dc, rest, np.array([d], np.float64), 1, clamp=False)[0]
        np.testing.assert_allclose(c, C0 * sh[0] + term + 0.5, rtol=1e-14)
    # through the renderer: view direction from the camera centre to the mean (world space)
    cam = sf.generic_camera(16, 12, variant=2)
    for d in [(1, 0, 0), (0, 1, 0), (0, 0, 1)]:
        mean = cam.center + 3.0 * np.array(d, np.float64)
        out = ref.render_reference(one(mean, dc=dc[0], rest=rest, degree=1), cam)
        np.testing.assert_allclose(out["colors"][0], np.maximum(C0 * sh[0] + axes[d] + 0.5, 0), rtol=1e-12)


def test_sh_higher_bands_closed_forms():
    # single coefficient at a time, direction (x, y, z) generic
    d = np.array([[0.36, -0.48, 0.8]])  # unit
    x, y, z = d[0]
    expect = [C0, -C1 * y, C1 * z, -C1 * x,
              ref.SH_C2[0] * x * y, ref.SH_C2[1] * y * z, ref.SH_C2[2] * (2 * z * z - x * x - y * y),
              ref.SH_C2[3] * x * z, ref.SH_C2[4] * (x * x - y * y),
              ref.SH_C3[0] * y * (3 * x * x - y * y), ref.SH_C3[1] * x * y * z, ref.SH_C3[2] * y * (4 * z * z - x * x - y * y),
              ref.SH_C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y), ref.SH_C3[4] * x * (4 * z * z - x * x - y * y),
              ref.SH_C3[5] * z * (x * x - y * y), ref.SH_C3[6] * x * (x * x - 3 * y * y)]
    for k in range(16):
        sh = np.zeros((1, 16, 3))
        sh[0, k] = [1.0, 2.0, -1.0]
        c = ref.sh_to_color(sh[:, 0], sh[:, 1:], d, 3, clamp=False)[0]
        np.testing.assert_allclose(c, expect[k] * np.array([1.0, 2.0, -1.0]) + 0.5, rtol=1e-14, atol=1e-15)
    # magnitudes: the known normalization constants of real SH
    assert C0 == pytest.approx(0.5 / math.sqrt(math.pi))
    assert C1 == pytest.approx(math.sqrt(3 / (4 * math.pi)))
    assert ref.SH_C2[0] == pytest.approx(0.5 * math.sqrt(15 / math.pi))
    assert ref.SH_C2[2] == pytest.approx(0.25 * math.sqrt(5 / math.pi))
    assert ref.SH_C2[4] == pytest.approx(0.25 * math.sqrt(15 / math.pi))
    assert abs(ref.SH_C3[0]) == pytest.approx(0.25 * math.sqrt(35 / (2 * math.pi)))
    assert abs(ref.SH_C3[1]) == pytest.approx(0.5 * math.sqrt(105 / math.pi))
    assert abs(ref.SH_C3[2]) == pytest.approx(0.25 * math.sqrt(21 / (2 * math.pi)))
    assert abs(ref.SH_C3[3]) == pytest.approx(0.25 * math.sqrt(7 / math.pi))


def test_sh_basis_is_orthonormal_on_the_sphere():
    # Gauss-Legendre in cos(theta) x uniform phi integrates polynomials of degree <= 6 exactly
    ct, wt = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * (2 * np.pi / 16)
    CT, PH = np.meshgrid(ct, phi, indexing="ij")
    st = np.sqrt(1 - CT**2)
    dirs = np.stack([st * np.cos(PH), st * np.sin(PH), CT], axis=-1).reshape(-1, 3)
    w = (wt[:, None] * np.full(16, 2 * np.pi / 16)[None, :]).reshape(-1)
    Y = ref.sh_basis(dirs, 3)
    gram = (Y * w[:, None]).T @ Y
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-12)


def test_sh_degree_selection():
    p, cam = sf.random_scene(2, n=10, sh_degree=3)
    full = ref.render_reference(p, cam)
    assert full["sh_degree"] == 3
    for deg in range(3):
        trunc = {**p, "sh_rest": p["sh_rest"][:, : (deg + 1) ** 2 - 1]}
        np.testing.assert_array_equal(ref.render_reference(p, cam, sh_degree=deg)["rgb"],
                                      ref.render_reference(trunc, cam)["rgb"])
    with pytest.raises(ValueError, match="sh_degree"):
        ref.render_reference(trunc, cam, sh_degree=3)


# ============================================================================================== gradients
def _random_weights(cam, seed=0):
    rng = np.random.default_rng(seed)
    return {"rgb": rng.normal(size=(cam.height, cam.width, 3)), "alpha": rng.normal(size=(cam.height, cam.width)),
            "depth": rng.normal(size=(cam.height, cam.width))}


def test_fd_gradients_match_analytic_single_gaussian():
    cam = sf.identity_camera(21, 17, fx=30.0)  # cx = 10.5, cy = 8.5
    z, sx, sy, sz, logit = 4.0, 0.25, 0.15, 0.4, 0.3
    dc = np.array([0.4, -0.2, 0.9])
    bg = np.array([0.1, 0.3, 0.2])
    p = one((0.1, -0.05, z), log_sigma=np.log([sx, sy, sz]), logit=logit, dc=dc)
    w = _random_weights(cam)
    # one Gaussian: depth = D / (1 - T) = t_z alpha / (1 - (1 - alpha)) = t_z = mean_z wherever alpha > 0, so only
    # mean_z moves it: d / d mean_z = sum of w_depth over the footprint. Its rounding noise (~1e-16 / alpha) divided by
    # 2 eps swamps finite differences at 1e-5 relative, so the depth weight is checked on its own, more loosely.
    footprint = ref.render_reference(p, cam)["alpha"] > 0
    g_depth = ref.fd_gradients(p, cam, {"depth": w["depth"]}, background=bg)
    for name, g in g_depth.items():
        expect = np.zeros_like(g)
        if name == "means":
            expect[0, 2] = w["depth"][footprint].sum()
        np.testing.assert_allclose(g, expect, atol=1e-6, err_msg=name)
    w = {"rgb": w["rgb"], "alpha": w["alpha"]}
    grads, bad = ref.fd_gradients(p, cam, w, background=bg, return_unreliable=True)
    assert not any(b.any() for b in bad.values())

    out = ref.render_reference(p, cam, background=bg)
    alpha = out["alpha"]
    assert alpha.max() < 0.99  # no clamp anywhere
    o = sigmoid(logit)
    c = C0 * dc + 0.5
    # d loss / d sh_dc = C0 * sum w_rgb * alpha * T (T = 1 in front)
    np.testing.assert_allclose(grads["sh_dc"][0], C0 * np.einsum("hwc,hw->c", w["rgb"], alpha), rtol=1e-6)
    # d alpha / d logit = alpha (1 - o) where it contributes; rgb = c alpha + bg (1 - alpha); depth = z (constant)
    dl_dalpha = np.einsum("hwc,c->hw", w["rgb"], c - bg) + w["alpha"]  # (depth does not move: its weight is off)
    np.testing.assert_allclose(grads["opacities"][0], np.sum(dl_dalpha * alpha * (1 - o)), rtol=1e-6)
    # scales: identity rotation and camera, Sigma = diag(s^2); the mean is off axis, so J's third column (-f x / z^2,
    # -f y / z^2) couples sz into Sigma2D too. Closed form: alpha = o exp(-0.5 d^T (J S J^T + 0.3 I)^-1 d), and
    # d(M^-1) = -M^-1 dM M^-1:
    X, Y = pixel_grid(cam)
    f = 30.0
    mx, my = f * 0.1 / z + 10.5, f * -0.05 / z + 8.5
    Jm = np.array([[f / z, 0, -f * 0.1 / z**2], [0, f / z, f * 0.05 / z**2]])

    def alpha_of(ls):
        S = np.diag(np.exp(2 * np.asarray(ls)))
        cov = Jm @ S @ Jm.T + 0.3 * np.eye(2)
        inv = np.linalg.inv(cov)
        dx, dy = mx - X, my - Y
        return o * np.exp(-0.5 * (inv[0, 0] * dx * dx + 2 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy)), cov, inv

    a_cf, cov, inv = alpha_of(np.log([sx, sy, sz]))
    mask = a_cf >= 1 / 255
    np.testing.assert_allclose(alpha, np.where(mask, a_cf, 0), rtol=1e-12, atol=1e-15)
    dx, dy = mx - X, my - Y
    dvec = np.stack([dx, dy], -1)
    for k in range(3):
        dS = np.zeros((3, 3))
        dS[k, k] = 2 * [sx, sy, sz][k] ** 2  # d exp(2 ls) / d ls
        dcov = Jm @ dS @ Jm.T
        dinv = -inv @ dcov @ inv
        dpower = -0.5 * np.einsum("hwi,ij,hwj->hw", dvec, dinv, dvec)
        dalpha = np.where(mask, a_cf * dpower, 0)
        np.testing.assert_allclose(grads["scales"][0, k], np.sum(dl_dalpha * dalpha), rtol=1e-5, atol=1e-9)
    # an isotropic Gaussian is invariant to its rotation
    p_iso = one((0.1, -0.05, z), log_sigma=(math.log(0.2),) * 3, rot=(0.9, 0.2, -0.1, 0.3), logit=logit, dc=dc)
    g_iso = ref.fd_gradients(p_iso, cam, w, background=bg, names=["rotations"])
    np.testing.assert_allclose(g_iso["rotations"], 0.0, atol=1e-7)


def test_fd_gradients_two_layers_back_colour():
    cam = sf.identity_camera(21, 17, fx=30.0)
    near = one((0.05, 0.0, 2.0), log_sigma=(math.log(0.1),) * 3, logit=0.5, dc=(0.2, 0.1, -0.3))
    far = one((0.0, 0.05, 3.0), log_sigma=(math.log(0.2),) * 3, logit=1.0, dc=(-0.2, 0.4, 0.3))
    p = stack(far, near)
    w = _random_weights(cam, 1)
    g = ref.fd_gradients(p, cam, w, names=["sh_dc"], index_subset=[0])
    assert np.isnan(g["sh_dc"][1]).all()  # entries outside the subset are NaN, never silently zero
    # d rgb / d sh_dc(far) = C0 alpha_far T_before_far = C0 alpha_far (1 - alpha_near)
    a_near = ref.render_reference(near, cam)["alpha"]
    a_far = ref.render_reference(far, cam)["alpha"]
    np.testing.assert_allclose(g["sh_dc"][0], C0 * np.einsum("hwc,hw->c", w["rgb"], a_far * (1 - a_near)), rtol=1e-6)


def test_batched_compositing_equals_one_scene_at_a_time():
    # the finite differences render perturbed scenes in batches: batching must not change a single bit
    p, cam = sf.near_plane()
    variants = []
    for k, dz in enumerate([0.0, 0.02, -0.02, 0.3]):  # different culled sets -> different list lengths (padding)
        q = {key: v.astype(np.float64).copy() for key, v in p.items()}
        q["means"] -= dz * cam.world_to_camera[2, :3]  # move everything along the view axis
        q["opacities"][k] += 0.5
        variants.append(q)
    pres = [ref.preprocess(q, cam) for q in variants]
    assert len({int((~pre["culled"]).sum()) for pre in pres}) > 1
    bg = (0.3, 0.2, 0.1)
    batch = ref.composite_batch(pres, cam, background=bg, record=True)
    for b, pre in enumerate(pres):
        single = ref.composite(pre, cam, background=bg, record=True)
        for key in ("rgb", "alpha", "depth", "final_T", "n_contrib", "last_contrib", "pixel_margin", "visible",
                    "order", "contrib_mask", "alpha_clamp_mask"):
            np.testing.assert_array_equal(batch[key][b], single[key], err_msg=key)


def test_depth_gap():
    p, cam = sf.equal_depths()
    out = ref.render_reference(p, cam)
    assert (out["depth_gap"] == 0).all()  # every Gaussian shares its mean with 3 others
    p, cam = sf.random_scene(0)
    out = ref.render_reference(p, cam)
    d = np.sort(out["depths"])
    assert out["depth_gap"].min() == pytest.approx(np.min(np.diff(d) / d[1:]), rel=1e-12)


def test_fd_gradients_flag_discontinuities():
    # a Gaussian exactly at the near plane: +eps keeps it, -eps culls it -> flagged unreliable
    cam = sf.identity_camera(21, 17, fx=30.0)
    p = one((0.0, 0.0, 0.2), log_sigma=(-6.0,) * 3, logit=1.0)
    _, bad = ref.fd_gradients(p, cam, _random_weights(cam), names=["means"], return_unreliable=True)
    assert bad["means"][0].tolist() == [False, False, True]


# ============================================================================================== invariances, determinism
def test_pose_invariance_world_vs_camera_space():
    # the same scene described in camera space (identity camera) and in world space (generic camera): same image
    # (SH degree 0, since higher bands are evaluated in world space and legitimately change)
    rng = np.random.default_rng(11)
    cam_w = sf.generic_camera(40, 32, variant=1, fx=38.0, fy=41.0, cx=17.0, cy=18.5)
    cam_c = Camera(40, 32, 38.0, 41.0, 17.0, 18.5, np.eye(4))
    n = 25
    px, py, z = rng.uniform(0, 40, n), rng.uniform(0, 32, n), rng.uniform(1.5, 6, n)
    means_c = np.stack([(px - 17.0) / 38.0 * z, (py - 18.5) / 41.0 * z, z], axis=1)
    q_c = sf.random_quaternions(rng, n)
    base = {"scales": np.log(rng.uniform(2, 6, (n, 3)) * z[:, None] / 40), "opacities": rng.uniform(-1, 3, n),
            "sh_dc": rng.normal(0, 1, (n, 3)), "sh_rest": np.zeros((n, 0, 3))}
    out_c = ref.render_reference({**base, "means": means_c, "rotations": q_c}, cam_c)
    p_w = {**base, "means": sf.camera_to_world(cam_w, means_c), "rotations": sf.camera_to_world_rotation(cam_w, q_c)}
    out_w = ref.render_reference(p_w, cam_w)
    safe = out_c["pixel_margin"] > 1e-6
    assert safe.mean() > 0.95
    for k in ("rgb", "alpha", "depth"):
        np.testing.assert_allclose(out_w[k][safe], out_c[k][safe], rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(out_w["cov2d"], out_c["cov2d"], rtol=1e-9)


def test_quaternion_norm_does_not_matter():
    p, cam = sf.random_scene(4, n=20, sh_degree=1)
    a = ref.render_reference(p, cam)
    for s in (1e-3, 1e3):
        b = ref.render_reference({**p, "rotations": p["rotations"].astype(np.float64) * s}, cam)
        np.testing.assert_allclose(b["rgb"], a["rgb"], rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="zero"):
        ref.render_reference({**p, "rotations": np.zeros_like(p["rotations"])}, cam)


def test_equal_depths_keep_index_order():
    cam = sf.identity_camera(33, 25, fx=40.0)
    red = one((0.0, 0.0, 3.0), logit=0.0, dc=(1.0, -1.7, -1.7))
    blue = one((0.0, 0.0, 3.0), logit=0.0, dc=(-1.7, -1.7, 1.0), log_sigma=(-1.0,) * 3)
    c_red, c_blue = np.maximum(C0 * red["sh_dc"][0] + 0.5, 0), np.maximum(C0 * blue["sh_dc"][0] + 0.5, 0)
    rb = ref.render_reference(stack(red, blue), cam)["rgb"][12, 16]
    br = ref.render_reference(stack(blue, red), cam)["rgb"][12, 16]
    np.testing.assert_allclose(rb, 0.5 * c_red + 0.25 * c_blue, rtol=1e-14)
    np.testing.assert_allclose(br, 0.5 * c_blue + 0.25 * c_red, rtol=1e-14)
    for name in ("equal_depths", "equal_depths_axis_aligned"):
        p, cam = sf.SCENES[name]()
        out = ref.render_reference(p, cam)
        d = out["depths"][out["order"]]
        assert (np.diff(d) >= 0).all()
        ties = np.diff(d) == 0
        assert ties.sum() >= 10, name
        assert (np.diff(out["order"])[ties] > 0).all()  # ties in index order


def test_determinism_and_inputs_untouched():
    p, cam = sf.many_layers()
    copy = {k: v.copy() for k, v in p.items()}
    a = ref.render_reference(p, cam, background=(0.1, 0.2, 0.3))
    b = ref.render_reference(p, cam, background=(0.1, 0.2, 0.3))
    for k in ("rgb", "alpha", "depth", "n_contrib", "means2d", "visible"):
        np.testing.assert_array_equal(a[k], b[k])
    for k in p:
        np.testing.assert_array_equal(p[k], copy[k])
        assert p[k].dtype == np.float32
    p2, cam2 = sf.many_layers()
    for k in p:
        np.testing.assert_array_equal(p[k], p2[k])  # scene generators are seeded


def test_vectorized_compositing_matches_a_scalar_loop():
    # the brief's per-pixel pseudo-code, literally, on the preprocessed Gaussians of two scenes
    for name in ("many_layers", "opacity_extremes"):
        p, cam = sf.SCENES[name]()
        bg = np.array([0.3, 0.6, 0.1])
        out = ref.render_reference(p, cam, background=bg)
        pre = ref.preprocess(p, cam)
        valid = [g for g in range(pre["n"]) if not pre["culled"][g]]
        order = sorted(valid, key=lambda g: (pre["depths"][g], g))
        for j in range(0, cam.height, 3):
            for i in range(0, cam.width, 3):
                T, C, D, n = 1.0, np.zeros(3), 0.0, 0
                for g in order:
                    dx = pre["means2d"][g, 0] - (i + 0.5)
                    dy = pre["means2d"][g, 1] - (j + 0.5)
                    ca, cb, cc = pre["conics"][g]
                    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    if power > 0:
                        continue
                    alpha = min(0.99, pre["opacities"][g] * math.exp(power))
                    if alpha < 1 / 255:
                        continue
                    test_T = T * (1 - alpha)
                    if test_T < 1e-4:
                        break
                    C += pre["colors"][g] * alpha * T
                    D += pre["depths"][g] * alpha * T
                    T = test_T
                    n += 1
                assert out["n_contrib"][j, i] == n
                np.testing.assert_allclose(out["rgb"][j, i], C + T * bg, rtol=1e-12, atol=1e-14)
                np.testing.assert_allclose(out["depth"][j, i], D / (1 - T) if T < 1 else 0.0, rtol=1e-12)


# ============================================================================================== the scene factory
@pytest.mark.parametrize("name", sorted(sf.SCENES))
def test_every_scene_renders_sanely(name):
    p, cam = sf.SCENES[name](seed=0)
    assert cam.width <= 64 and cam.height <= 64
    for k, v in p.items():
        assert v.dtype == np.float32, k
    n = p["means"].shape[0]
    assert p["rotations"].shape == (n, 4) and (np.linalg.norm(p["rotations"], axis=1) > 0).all()
    bg = np.array([0.2, 0.4, 0.6])
    out = ref.render_reference(p, cam, background=bg)
    for k in ("rgb", "alpha", "depth"):
        assert np.isfinite(out[k]).all(), k
    assert (out["alpha"] >= 0).all() and (out["final_T"] >= 1e-4).all()
    assert not (out["visible"] & out["culled"]).any()
    # visible <=> it is some pixel's contributor (checked through the last contributor as a lower bound)
    assert set(np.unique(out["last_contrib"][out["last_contrib"] >= 0])) <= set(np.nonzero(out["visible"])[0])
    if out["visible"].any():
        d = out["depths"][out["visible"]]
        hit = out["alpha"] > 0
        assert (out["depth"][hit] >= d.min() * (1 - 1e-12)).all() and (out["depth"][hit] <= d.max() * (1 + 1e-12)).all()
    np.testing.assert_array_equal(out["rgb"][out["n_contrib"] == 0], np.broadcast_to(bg, ((out["n_contrib"] == 0).sum(), 3)))
    # float32 mode agrees away from thresholds
    out32 = ref.render_reference(p, cam, background=bg, dtype=np.float32)
    safe = out["pixel_margin"] > 1e-3
    assert np.abs(out32["rgb"] - out["rgb"])[safe].max(initial=0) < 1e-4


def test_scene_factory_covers_its_cases():
    p, cam = sf.behind_camera()
    _, tz = cam.project(p["means"].astype(np.float64))
    assert (tz < 0).sum() >= 10 and (tz > 0.2).sum() >= 10
    out = ref.render_reference(*sf.opacity_extremes())
    assert out["visible"].tolist()[:3] == [False, False, True]
    out = ref.render_reference(*sf.many_layers())
    assert (out["final_T"] < 2e-4).sum() > 0  # early termination actually happens
    out = ref.render_reference(*sf.border_and_outside())
    assert out["guard_clamped"].any(axis=1).sum() >= 10 and out["visible"][out["guard_clamped"].any(axis=1)].any()
    out = ref.render_reference(*sf.extreme_scales())
    assert out["alpha"].min() > 0.5  # huge Gaussians cover the whole image
    tiny = ref.render_reference(*sf.extreme_scales())["cov2d"][:30]
    assert np.allclose(tiny[:, 0, 0], 0.3, rtol=1e-3)  # dilation dominates
    out64 = ref.render_reference(*sf.opaque_stack())
    out32 = ref.render_reference(*sf.opaque_stack(), dtype=np.float32)
    assert (out64["n_contrib"] != out32["n_contrib"]).any()  # the deliberate float32/float64 hazard is present
    for name, (w, h) in {"odd_size_37x53": (37, 53), "odd_size_61x17": (61, 17)}.items():
        _, cam = sf.SCENES[name]()
        assert (cam.width, cam.height) == (w, h)
    _, cam = sf.principal_point_off_centre()
    assert cam.cx != cam.width / 2 and cam.cy != cam.height / 2 and cam.fx != cam.fy
    R = sf.generic_camera().world_to_camera[:3, :3]
    assert (np.abs(R) > 0.05).sum() >= 7  # not axis aligned


def test_reference_is_independent_of_the_fast_rasterizer():
    import ast

    here = os.path.dirname(__file__)
    for fname in ("reference.py", "scene_factory.py", "test_reference.py"):
        with open(os.path.join(here, fname), encoding="utf-8") as f:
            tree = ast.parse(f.read())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                mods = [node.module or ""] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            assert not any(m.startswith("mi_gaussians.raster") for m in mods), (fname, mods)
    # the reference module itself imports nothing of the package (it only duck-types the camera)
    import subprocess

    code = ("import sys; sys.path.insert(0, %r); import reference; "
            "print(sorted(m for m in sys.modules if m.startswith('mi_gaussians')))" % here)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "[]"
