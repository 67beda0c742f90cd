"""Seeded test scenes for the rasterizer: ``(params, camera)`` pairs, small images (<= 64 x 64).

``params`` holds raw 3DGS parameters as float32 NumPy arrays (so a float32 implementation sees exactly the values the
float64 reference sees): means (N, 3), scales (N, 3) log-sigma, rotations (N, 4) unnormalized (w, x, y, z),
opacities (N,) logits, sh_dc (N, 3), sh_rest (N, K - 1, 3) coefficient-major (band index, then RGB).

Gaussians are placed in camera space (pixel position + depth) and mapped to world space through a generic
(not axis-aligned) look-at camera, so every scene exercises the full world -> camera transform. Because the world
coordinates are rounded to float32, a camera-space depth given here is only exact to ~1e-7 relative; scenes that
probe a threshold keep a margin of at least 5e-4 from it (near plane) unless stated otherwise.

Every scene function takes ``seed`` and returns ``(params, camera)``; ``SCENES`` maps names to them, e.g.::

    for name, make in SCENES.items():
        params, cam = make(seed=0)
"""

from __future__ import annotations

import math

import numpy as np

try:
    from mi_gaussians.data.camera import Camera
except Exception:  # pragma: no cover - the package failed to import (e.g. a plugin mid-development): keep the oracle
    # usable by loading the camera record (plain NumPy) on its own; fast-rasterizer tests need the package anyway
    import importlib.util
    import pathlib
    import sys

    _path = pathlib.Path(__file__).resolve().parents[1] / "mi_gaussians" / "data" / "camera.py"
    _spec = importlib.util.spec_from_file_location("_mi_gaussians_camera_standalone", _path)
    _mod = importlib.util.module_from_spec(_spec)
    sys.modules[_spec.name] = _mod  # dataclasses look their module up
    _spec.loader.exec_module(_mod)
    Camera = _mod.Camera

SH_C0 = 0.28209479177387814


# ---------------------------------------------------------------------------------------------- cameras
def look_at(eye, target, up=(0.0, 0.0, 1.0), width: int = 64, height: int = 48, fx: float | None = None,
            fy: float | None = None, cx: float | None = None, cy: float | None = None, fov_x_deg: float = 60.0,
            name: str = "") -> Camera:
    """A camera at ``eye`` looking at ``target`` (OpenCV axes: x right, y down = -up, z forward)."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    if fx is None:
        fx = width / (2.0 * math.tan(math.radians(fov_x_deg) / 2.0))
    fy = fx if fy is None else fy
    cx = width / 2.0 if cx is None else cx
    cy = height / 2.0 if cy is None else cy
    return Camera(width, height, fx, fy, cx, cy, w2c, name)


def generic_camera(width: int = 64, height: int = 48, variant: int = 0, **kw) -> Camera:
    """A fixed, generic (non-axis-aligned) pose; ``variant`` picks one of a few."""
    eyes = [(2.3, -3.1, 1.7), (-2.9, -1.3, 2.2), (0.7, 3.4, -1.1)]
    targets = [(0.1, 0.2, -0.05), (0.3, -0.2, 0.15), (-0.1, 0.05, 0.2)]
    ups = [(0.05, 0.1, 1.0), (-0.1, 0.03, 1.0), (0.2, -0.1, 1.0)]
    k = variant % len(eyes)
    return look_at(eyes[k], targets[k], ups[k], width, height, **kw)


def identity_camera(width: int = 64, height: int = 48, fx: float = 50.0, fy: float | None = None,
                    cx: float | None = None, cy: float | None = None) -> Camera:
    """A camera at the origin looking down +z with OpenCV axes (world == camera space)."""
    return Camera(width, height, fx, fx if fy is None else fy, width / 2.0 if cx is None else cx,
                  height / 2.0 if cy is None else cy, np.eye(4))


def camera_to_world(camera: Camera, pts_cam) -> np.ndarray:
    """Camera-space points (N, 3) -> world space."""
    pts_cam = np.asarray(pts_cam, np.float64).reshape(-1, 3)
    R, t = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3]
    return (pts_cam - t) @ R  # R^T (p - t) for each row


def pixel_to_world(camera: Camera, px, py, depth) -> np.ndarray:
    """World points whose projection is pixel coordinates (px, py) at camera-space depth ``depth``."""
    px, py, depth = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (px, py, depth)))
    xc = (px - camera.cx) / camera.fx * depth
    yc = (py - camera.cy) / camera.fy * depth
    return camera_to_world(camera, np.stack([xc, yc, depth], axis=-1).reshape(-1, 3))


def camera_to_world_rotation(camera: Camera, q_cam) -> np.ndarray:
    """Quaternions (w, x, y, z) of rotations given in camera axes -> the same physical rotations in world axes."""
    R = camera.world_to_camera[:3, :3]  # world -> camera
    q_wc = matrix_to_quaternion(R.T)     # camera -> world as a quaternion
    return quaternion_multiply(np.broadcast_to(q_wc, np.shape(q_cam)), np.asarray(q_cam, np.float64))


# ---------------------------------------------------------------------------------------------- quaternions
def quaternion_multiply(a, b) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions (N, 4)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def matrix_to_quaternion(R) -> np.ndarray:
    """A rotation matrix (3, 3) -> unit quaternion (w, x, y, z) (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    return np.asarray(q)


def random_quaternions(rng, n: int, norm_range=(0.5, 2.0)) -> np.ndarray:
    """Uniform random rotations as (w, x, y, z), multiplied by a random norm in ``norm_range`` (never zero)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * rng.uniform(*norm_range, size=(n, 1))


def quaternion_z_to(direction) -> np.ndarray:
    """Unit quaternion rotating the local +z axis onto ``direction`` (N, 3)."""
    d = np.asarray(direction, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(np.broadcast_to(z, d.shape), d)
    s = np.linalg.norm(axis, axis=1)
    angle = np.arctan2(s, d @ z)
    axis = np.where(s[:, None] > 1e-12, axis / np.maximum(s, 1e-300)[:, None], np.array([1.0, 0.0, 0.0]))
    return np.concatenate([np.cos(angle / 2)[:, None], np.sin(angle / 2)[:, None] * axis], axis=1)


# ---------------------------------------------------------------------------------------------- parameters
def logit(p) -> np.ndarray:
    p = np.asarray(p, np.float64)
    return np.log(p / (1.0 - p))


def make_params(means, scales, rotations, opacities, sh_dc, sh_rest=None, sh_degree: int = 0) -> dict:
    """Pack raw parameters as float32 arrays with canonical shapes (sh_rest zeros of the given degree if None)."""
    means = np.asarray(means, np.float32).reshape(-1, 3)
    n = means.shape[0]
    if sh_rest is None:
        sh_rest = np.zeros((n, (sh_degree + 1) ** 2 - 1, 3))
    sh_rest = np.asarray(sh_rest, np.float32)
    if sh_rest.ndim != 3:
        sh_rest = sh_rest.reshape(n, -1, 3)
    return {
        "means": means,
        "scales": np.asarray(scales, np.float32).reshape(n, 3),
        "rotations": np.asarray(rotations, np.float32).reshape(n, 4),
        "opacities": np.asarray(opacities, np.float32).reshape(n),
        "sh_dc": np.asarray(sh_dc, np.float32).reshape(n, 3),
        "sh_rest": sh_rest,
    }


def random_sh(rng, n: int, degree: int, dc_scale: float = 1.2, rest_scale: float = 0.25):
    """Random SH: DC from random colours in [0.05, 0.95] ((rgb - 0.5) / C0) plus a little noise, small higher bands."""
    rgb = rng.uniform(0.05, 0.95, size=(n, 3))
    dc = (rgb - 0.5) / SH_C0 + rng.normal(0.0, 0.1 * dc_scale, size=(n, 3))
    rest = rng.normal(0.0, rest_scale, size=(n, (degree + 1) ** 2 - 1, 3))
    return dc, rest


def _random_gaussians(rng, cam: Camera, n: int, degree: int, depth=(2.0, 8.0), margin: float = 0.1,
                      sigma_px=(0.3, 6.0), aniso: float = 0.6, logit_range=(-2.0, 4.0)) -> dict:
    """n random Gaussians in the frustum: pixel position (image +- margin), depth, sigma given in pixels at that depth."""
    W, H = cam.width, cam.height
    px = rng.uniform(-margin * W, (1 + margin) * W, n)
    py = rng.uniform(-margin * H, (1 + margin) * H, n)
    z = rng.uniform(*depth, n)
    means = pixel_to_world(cam, px, py, z)
    sigma_world = np.exp(rng.uniform(np.log(sigma_px[0]), np.log(sigma_px[1]), n)) * z / cam.fx
    scales = np.log(sigma_world)[:, None] + rng.normal(0.0, aniso, size=(n, 3))
    rots = random_quaternions(rng, n)
    opac = rng.uniform(*logit_range, n)
    dc, rest = random_sh(rng, n, degree)
    return make_params(means, scales, rots, opac, dc, rest)


def concat_params(*ps: dict) -> dict:
    """Concatenate parameter dicts (the SH degree must agree)."""
    return {k: np.concatenate([p[k] for p in ps], axis=0) for k in ps[0]}


# ---------------------------------------------------------------------------------------------- scenes
def random_scene(seed: int = 0, n: int = 50, sh_degree: int | None = None, width: int = 64, height: int = 48,
                 fx: float | None = None, fy: float | None = None, cx: float | None = None, cy: float | None = None,
                 variant: int = 0):
    """n random anisotropic Gaussians in front of a generic camera; SH degree random in 0..3 unless given."""
    rng = np.random.default_rng(seed)
    degree = int(rng.integers(0, 4)) if sh_degree is None else sh_degree
    cam = generic_camera(width, height, variant=variant, fx=fx, fy=fy, cx=cx, cy=cy)
    return _random_gaussians(rng, cam, n, degree), cam


def behind_camera(seed: int = 0, n_front: int = 12, n_behind: int = 12):
    """Half the Gaussians behind the camera (t_z in [-5, -0.01]) whose mirrored projection lands in the image."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(48, 40, variant=1)
    front = _random_gaussians(rng, cam, n_front, 1)
    back = _random_gaussians(rng, cam, n_behind, 1, depth=(0.01, 5.0), sigma_px=(2.0, 20.0))
    # mirror through the camera centre: camera-space (x, y, z) -> (-x, -y, -z), same |projection| ratios
    c = cam.center
    back["means"] = (2 * c - back["means"].astype(np.float64)).astype(np.float32)
    # and a few big ones with a (culled) mean just behind the camera whose extent reaches far in front
    big = make_params(camera_to_world(cam, [[0.0, 0.0, -0.05], [0.1, -0.05, -0.5]]), np.log([[2.0] * 3, [3.0] * 3]),
                      [[1, 0, 0, 0]] * 2, [4.0, 4.0], np.zeros((2, 3)), np.zeros((2, 3, 3)))
    return concat_params(front, back, big), cam


def near_plane(seed: int = 0):
    """Gaussians straddling the near plane t_z = 0.2: just in front / just behind (margin >= 5e-4) and big culled ones."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(40, 32, variant=2)
    zs = np.array([0.05, 0.15, 0.19, 0.199, 0.1995, 0.2005, 0.201, 0.21, 0.25, 0.3, 0.5])
    n = len(zs)
    px = rng.uniform(0.3 * cam.width, 0.7 * cam.width, n)
    py = rng.uniform(0.3 * cam.height, 0.7 * cam.height, n)
    means = pixel_to_world(cam, px, py, zs)
    scales = np.log(rng.uniform(0.002, 0.02, size=(n, 3)))
    dc, rest = random_sh(rng, n, 2)
    near = make_params(means, scales, random_quaternions(rng, n), rng.uniform(-1, 2, n), dc, rest)
    # big Gaussians (sigma 1-3) whose mean is at or behind the near plane but whose extent reaches well in front: culled
    bz = np.array([-0.5, -0.05, 0.1, 0.19])
    bmeans = camera_to_world(cam, np.stack([np.zeros(4), np.zeros(4), bz], axis=1))
    dc2, rest2 = random_sh(rng, 4, 2)
    big = make_params(bmeans, np.log(rng.uniform(1.0, 3.0, size=(4, 3))), random_quaternions(rng, 4),
                      np.full(4, 3.0), dc2, rest2)
    # and a normal background layer so the image is not empty
    bg = _random_gaussians(rng, cam, 10, 2, depth=(3.0, 6.0))
    return concat_params(near, big, bg), cam


def extreme_scales(seed: int = 0):
    """Huge Gaussians (sigma >> image; 10-1000 world units at depth ~5) and tiny ones (sigma ~ 1e-5 px: 0.3 dominates)."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(48, 40, variant=0)
    n_huge, n_tiny = 4, 30
    huge_means = pixel_to_world(cam, rng.uniform(-20, 68, n_huge), rng.uniform(-20, 60, n_huge),
                                rng.uniform(4, 8, n_huge))
    huge_scales = np.log(np.array([[10.0, 10.0, 10.0], [50.0, 20.0, 80.0], [1000.0, 1000.0, 1000.0],
                                   [30.0, 300.0, 3.0]]))
    dc, rest = random_sh(rng, n_huge, 1)
    huge = make_params(huge_means, huge_scales, random_quaternions(rng, n_huge), rng.uniform(-3.0, -1.0, n_huge),
                       dc, rest)
    tiny = _random_gaussians(rng, cam, n_tiny, 1, depth=(1.0, 4.0), sigma_px=(1e-5, 1e-3), aniso=1.0,
                             logit_range=(0.0, 6.0))
    return concat_params(tiny, huge), cam


def opacity_extremes(seed: int = 0):
    """Opacity logits -10 (never contributes), just below / above 1/255 (x0.99 / x1.01) and +10, +20 (0.99 clamp)."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(48, 40, variant=1)
    logits = np.array([-10.0, logit(0.99 / 255), logit(1.01 / 255), 10.0, 20.0, 10.0, 0.0, -3.0])
    n = len(logits)
    px = np.linspace(8, 40, n) + rng.uniform(-1, 1, n)
    py = np.full(n, 20.0) + rng.uniform(-5, 5, n)
    means = pixel_to_world(cam, px, py, np.linspace(2.0, 4.0, n))
    scales = np.log(3.0 * np.linspace(2.0, 4.0, n) / cam.fx)[:, None] + rng.normal(0, 0.2, (n, 3))
    dc, rest = random_sh(rng, n, 0)
    return make_params(means, scales, random_quaternions(rng, n), logits, dc, rest), cam


def degenerate_rotations(seed: int = 0):
    """Quaternions of norm 1e-3 and 1e3 (never zero), flat disks (one log-scale -20) facing and edge-on, needles
    (two log-scales -20) and points (all three -20: only the 0.3 dilation is left)."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(48, 40, variant=2)
    n = 14
    px = rng.uniform(4, 44, n)
    py = rng.uniform(4, 36, n)
    z = rng.uniform(2.0, 5.0, n)
    means = pixel_to_world(cam, px, py, z)
    s = np.log(4.0 * z / cam.fx)  # ~4 px
    scales = np.stack([s, s + 0.3, s - 0.2], axis=1)
    rots = random_quaternions(rng, n)
    rots[0:3] *= 1e-3 / np.linalg.norm(rots[0:3], axis=1, keepdims=True)   # tiny norm
    rots[3:6] *= 1e3 / np.linalg.norm(rots[3:6], axis=1, keepdims=True)    # large norm
    view = means - cam.center
    # flat disks: local z squashed; 6, 7 face the camera (local z along the view ray), 8, 9 edge-on
    scales[6:10, 2] = -20.0
    rots[6:8] = quaternion_z_to(view[6:8])
    perp = np.cross(view[8:10], np.array([0.3, -0.5, 0.8]))
    rots[8:10] = quaternion_z_to(perp)
    scales[10:12, 0:2] = -20.0  # needles
    scales[12:14, :] = -20.0    # points
    dc, rest = random_sh(rng, n, 3)
    return make_params(means, scales, rots, rng.uniform(0.5, 3.0, n), dc, rest), cam


def empty_scene(seed: int = 0, sh_degree: int = 0):
    """N = 0."""
    cam = generic_camera(32, 24)
    z = np.zeros((0, 3))
    return make_params(z, z, np.zeros((0, 4)), np.zeros(0), z, np.zeros((0, (sh_degree + 1) ** 2 - 1, 3))), cam


def single_gaussian(seed: int = 0, sh_degree: int = 1):
    """N = 1, anisotropic, near the image centre."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(32, 24)
    mean = pixel_to_world(cam, 15.3, 11.7, 3.0)
    dc, rest = random_sh(rng, 1, sh_degree)
    return make_params(mean, np.log([[0.15, 0.05, 0.1]]), random_quaternions(rng, 1), [1.5], dc, rest), cam


def many_layers(seed: int = 0, n: int = 200):
    """n Gaussians stacked over the same pixel region (distinct depths 2..6) so T < 1e-4 early termination triggers."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(32, 32, variant=1)
    px = cam.cx + rng.uniform(-3, 3, n)
    py = cam.cy + rng.uniform(-3, 3, n)
    z = rng.permutation(np.linspace(2.0, 6.0, n))  # index order != depth order
    means = pixel_to_world(cam, px, py, z)
    scales = np.log(rng.uniform(3.0, 8.0, n) * z / cam.fx)[:, None] + rng.normal(0, 0.3, (n, 3))
    dc, rest = random_sh(rng, n, 1)
    return make_params(means, scales, random_quaternions(rng, n), rng.uniform(-0.5, 3.0, n), dc, rest), cam


def opaque_stack(seed: int = 0, n: int = 12):
    """n near-opaque Gaussians (logit +10: alpha clamps at 0.99) stacked over the image centre at distinct depths.

    Hazard this probes on purpose: with two layers at alpha = 0.99, T = (1 - 0.99)^2 is 1.0000000000000018e-4 >= 1e-4 in
    float64 (both contribute) but 9.99998e-5 < 1e-4 in float32 (only the first does). Compare a float32
    implementation against ``render_reference(..., dtype=np.float32)`` here, or mask by ``pixel_margin``."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(32, 24, variant=2)
    px = cam.cx + rng.uniform(-1, 1, n)
    py = cam.cy + rng.uniform(-1, 1, n)
    z = rng.permutation(np.linspace(2.0, 5.0, n))
    means = pixel_to_world(cam, px, py, z)
    scales = np.log(rng.uniform(8.0, 16.0, n) * z / cam.fx)[:, None] + rng.normal(0, 0.2, (n, 3))
    dc, rest = random_sh(rng, n, 0)
    return make_params(means, scales, random_quaternions(rng, n), np.full(n, 10.0), dc, rest), cam


def principal_point_off_centre(seed: int = 0):
    """64 x 48 with cx = 0.3 W, cy = 0.7 H and fx != fy."""
    return random_scene(seed, n=40, width=64, height=48, fx=50.0, fy=58.0, cx=0.3 * 64, cy=0.7 * 48, variant=1)


def odd_size_37x53(seed: int = 0):
    """37 x 53 (not a multiple of 16), off-centre principal point."""
    return random_scene(seed, n=40, width=37, height=53, fx=40.0, fy=41.5, cx=17.2, cy=29.9, variant=2)


def odd_size_61x17(seed: int = 0):
    """61 x 17 (wide, not a multiple of 16)."""
    return random_scene(seed, n=30, width=61, height=17, variant=0)


def border_and_outside(seed: int = 0):
    """Gaussians near the image border, and far outside it (beyond the guard band) but big enough to reach in."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(48, 40, variant=0)
    W, H = cam.width, cam.height
    n_b = 16
    side = rng.integers(0, 4, n_b)
    t = rng.uniform(0, 1, n_b)
    off = rng.uniform(-3, 3, n_b)
    px = np.where(side == 0, off, np.where(side == 1, W + off, t * W))
    py = np.where(side == 2, off, np.where(side == 3, H + off, t * H))
    zb = rng.uniform(2, 6, n_b)
    sb = np.log(rng.uniform(1.0, 5.0, n_b) * zb / cam.fx)[:, None] + rng.normal(0, 0.4, (n_b, 3))
    dc, rest = random_sh(rng, n_b, 2)
    border = make_params(pixel_to_world(cam, px, py, zb), sb, random_quaternions(rng, n_b), rng.uniform(0, 3, n_b),
                         dc, rest)
    # far outside: projected 0.3 W .. 1.5 W beyond an edge (guard band [-0.15, 1.15] clamps J), large in world
    n_o = 12
    side = np.arange(n_o) % 4
    beyond = rng.uniform(0.3, 1.5, n_o)
    t = rng.uniform(0.2, 0.8, n_o)
    px = np.where(side == 0, -beyond * W, np.where(side == 1, (1 + beyond) * W, t * W))
    py = np.where(side == 2, -beyond * H, np.where(side == 3, (1 + beyond) * H, t * H))
    zo = rng.uniform(2, 5, n_o)
    so = np.log((beyond * max(W, H)) * zo / cam.fx * rng.uniform(0.4, 0.8, n_o))[:, None] + rng.normal(0, 0.3, (n_o, 3))
    dc, rest = random_sh(rng, n_o, 2)
    outside = make_params(pixel_to_world(cam, px, py, zo), so, random_quaternions(rng, n_o), rng.uniform(0, 2, n_o),
                          dc, rest)
    return concat_params(border, outside), cam


def equal_depths(seed: int = 0):
    """Depth ties: groups of Gaussians sharing exactly the same mean (identical depth in any implementation), with
    different colours / shapes / opacities; ties must keep index order."""
    rng = np.random.default_rng(seed)
    cam = generic_camera(40, 32, variant=1)
    groups, per = 5, 4
    px = rng.uniform(8, 32, groups)
    py = rng.uniform(6, 26, groups)
    z = rng.uniform(2, 5, groups)
    centres = pixel_to_world(cam, px, py, z).astype(np.float32)
    means = np.repeat(centres, per, axis=0)
    means = means[rng.permutation(len(means))]  # interleave the groups in index order
    n = len(means)
    zz = np.linalg.norm(means - cam.center, axis=1)
    scales = np.log(rng.uniform(2.0, 6.0, n) * zz / cam.fx)[:, None] + rng.normal(0, 0.3, (n, 3))
    dc, rest = random_sh(rng, n, 1)
    return make_params(means, scales, random_quaternions(rng, n), rng.uniform(0.5, 3.0, n), dc, rest), cam


def equal_depths_axis_aligned(seed: int = 0):
    """Depth ties with different means: an identity camera, so t_z == mean_z exactly in any float arithmetic."""
    rng = np.random.default_rng(seed)
    cam = identity_camera(40, 32, fx=45.0)
    n = 16
    zs = np.repeat(np.array([2.0, 3.0, 3.5, 5.0], np.float32), 4)[rng.permutation(n)]
    px = rng.uniform(10, 30, n)
    py = rng.uniform(8, 24, n)
    means = np.stack([(px - cam.cx) / cam.fx * zs, (py - cam.cy) / cam.fy * zs, zs], axis=1).astype(np.float32)
    means[:, 2] = zs
    scales = np.log(rng.uniform(3.0, 7.0, n) * zs / cam.fx)[:, None] + rng.normal(0, 0.3, (n, 3))
    dc, rest = random_sh(rng, n, 0)
    return make_params(means, scales, random_quaternions(rng, n), rng.uniform(0.5, 3.0, n), dc, rest), cam


SCENES = {
    "random_deg0": lambda seed=0: random_scene(seed, sh_degree=0),
    "random_deg1": lambda seed=0: random_scene(seed, sh_degree=1),
    "random_deg2": lambda seed=0: random_scene(seed, sh_degree=2),
    "random_deg3": lambda seed=0: random_scene(seed, sh_degree=3),
    "behind_camera": behind_camera,
    "near_plane": near_plane,
    "extreme_scales": extreme_scales,
    "opacity_extremes": opacity_extremes,
    "degenerate_rotations": degenerate_rotations,
    "empty": empty_scene,
    "single": single_gaussian,
    "many_layers": many_layers,
    "opaque_stack": opaque_stack,
    "principal_point_off_centre": principal_point_off_centre,
    "odd_size_37x53": odd_size_37x53,
    "odd_size_61x17": odd_size_61x17,
    "border_and_outside": border_and_outside,
    "equal_depths": equal_depths,
    "equal_depths_axis_aligned": equal_depths_axis_aligned,
}
