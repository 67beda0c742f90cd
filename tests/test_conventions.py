"""Layout converters (conventions.py) and SH evaluation (model/sh.py)."""

from __future__ import annotations

import ast
import inspect
import math

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

import reference
from mi_gaussians import conventions as cv
from mi_gaussians.model import sh
from mi_gaussians.model.gaussians import Gaussians


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    mi.set_variant(variant)     # (test_plugins switches variants: start each module on the run's own)


def sh_basis_numpy(dirs, degree):
    """The reference basis in float64 (the independent oracle of tests/reference.py): (N, (degree + 1)^2)."""
    return reference.sh_basis(np.asarray(dirs, np.float64).reshape(-1, 3), degree)


def eval_sh_numpy(sh_dc, sh_rest, dirs, degree):
    """Float64 reference of ``sh.eval_sh_colors``: sh_dc (N, 3), sh_rest (N, K - 1, 3), dirs (N, 3), unnormalized."""
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    rest = np.asarray(sh_rest, np.float64).reshape(d.shape[0], -1, 3)
    return reference.sh_to_color(np.asarray(sh_dc, np.float64).reshape(-1, 3), rest, d, degree)


def rand_dirs(n, seed=0, unit=True):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    if unit:
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d


def vec3(a: np.ndarray) -> "mi.Vector3f":
    return mi.Vector3f(np.ascontiguousarray(np.asarray(a, np.float32).T))


def np3(v) -> np.ndarray:
    return np.stack([np.array(v[i]) for i in range(3)], axis=1)


# ---------------------------------------------------------------------------------------------------- conventions
def test_quaternion_order():
    q = np.array([[1.0, 2.0, 3.0, 4.0]], np.float32)
    assert np.array_equal(cv.quat_wxyz_to_xyzw(q), [[2.0, 3.0, 4.0, 1.0]])
    assert np.array_equal(cv.quat_xyzw_to_wxyz(cv.quat_wxyz_to_xyzw(q)), q)
    assert cv.quat_wxyz_to_xyzw(q).dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(cv.normalize_quat(q), axis=1), 1.0, rtol=1e-6)
    with pytest.raises(ValueError):
        cv.quat_wxyz_to_xyzw(np.zeros((2, 3)))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_layouts(degree):
    k = (degree + 1) ** 2 - 1
    rng = np.random.default_rng(degree)
    rest = rng.normal(size=(7, k, 3)).astype(np.float32)
    f_rest = cv.sh_coeff_major_to_channel_major(rest)
    assert f_rest.shape == (7, 3 * k)
    for c in range(3):          # all R, then all G, then all B
        for j in range(k):
            assert f_rest[:, c * k + j].tobytes() == rest[:, j, c].tobytes()
    back = cv.sh_channel_major_to_coeff_major(f_rest)
    assert back.flags.c_contiguous and back.tobytes() == rest.tobytes()
    assert cv.sh_degree_from_coeff_count(k + 1) == degree
    assert cv.sh_coeff_count(degree) == k + 1 and cv.sh_degree_from_coeff_count(cv.sh_coeff_count(degree)) == degree
    with pytest.raises(ValueError):
        cv.sh_channel_major_to_coeff_major(np.zeros((2, 10)))
    with pytest.raises(ValueError):
        cv.sh_degree_from_coeff_count(k + 2)


def test_rgb_dc_sigmoid_logit():
    assert cv.SH_C0 == 0.28209479177387814
    assert abs(cv.SH_C0 - 1 / (2 * math.sqrt(math.pi))) < 1e-16
    rgb = np.random.default_rng(0).random((5, 3)).astype(np.float32)
    dc = cv.rgb_to_sh_dc(rgb)
    assert dc.dtype == np.float32
    np.testing.assert_allclose(dc, (rgb.astype(np.float64) - 0.5) / cv.SH_C0, rtol=1e-6)
    np.testing.assert_allclose(cv.sh_dc_to_rgb(dc), rgb, atol=1e-6)
    with np.errstate(all="raise"):
        s = cv.sigmoid(np.array([-1000.0, -30.0, 0.0, 30.0, 1000.0]))
    assert s[0] == 0.0 and s[2] == 0.5 and s[4] == 1.0 and 0 < s[1] < 1e-12
    x = np.linspace(-15, 15, 31)
    np.testing.assert_allclose(cv.logit(cv.sigmoid(x)), x, atol=1e-9)
    assert cv.sigmoid(np.float32(0.3)).dtype == np.float32
    for bad in (0.0, 1.0, -0.1, np.nan):
        with pytest.raises(ValueError):
            cv.logit(np.array([0.5, bad]))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ellipsoids_layout_round_trip(degree):
    rng = np.random.default_rng(degree)
    n, k = 9, (degree + 1) ** 2 - 1
    raw = {"means": rng.normal(size=(n, 3)), "scales": rng.normal(size=(n, 3)) - 2,
           "rotations": rng.normal(size=(n, 4)), "opacities": rng.normal(size=n) * 2,
           "sh_dc": rng.normal(size=(n, 3)), "sh_rest": rng.normal(size=(n, k, 3))}
    raw = {key: v.astype(np.float32) for key, v in raw.items()}
    lay = cv.to_ellipsoids_layout(**raw)
    assert lay["data"].shape == (n, cv.ELLIPSOID_STRUCT_SIZE) and lay["sh_coeffs"].shape == (n, 3 * (k + 1))
    assert all(v.dtype == np.float32 for v in lay.values())
    assert np.array_equal(lay["data"][:, :3], raw["means"])
    np.testing.assert_allclose(lay["data"][:, 3:6], np.exp(raw["scales"].astype(np.float64)), rtol=3e-7)
    q = raw["rotations"].astype(np.float64)
    np.testing.assert_allclose(lay["data"][:, 6:], (q / np.linalg.norm(q, axis=1, keepdims=True))[:, [1, 2, 3, 0]],
                               atol=2e-7)
    for j in range(k + 1):      # interleaved: [c_j R, c_j G, c_j B] for j = 0 (DC), 1, ...
        src = raw["sh_dc"] if j == 0 else raw["sh_rest"][:, j - 1]
        assert np.array_equal(lay["sh_coeffs"][:, 3 * j:3 * j + 3], src)
    back = cv.from_ellipsoids_layout(lay["data"].reshape(-1), lay["opacities"][:, None], lay["sh_coeffs"].reshape(-1))
    assert np.array_equal(back["means"], raw["means"])
    np.testing.assert_allclose(back["scales"], raw["scales"], atol=1e-6)
    np.testing.assert_allclose(back["opacities"], raw["opacities"], atol=1e-4)
    assert np.array_equal(back["sh_dc"], raw["sh_dc"]) and np.array_equal(back["sh_rest"], raw["sh_rest"])
    np.testing.assert_allclose(back["rotations"], cv.normalize_quat(raw["rotations"]), atol=2e-7)
    # the result feeds Gaussians directly
    assert Gaussians.from_numpy(**back).sh_degree == degree


# ---------------------------------------------------------------------------------------------------- SH basis
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_basis_equals_drjit_sh_eval(degree):
    d = rand_dirs(257, seed=degree)
    ours = sh.sh_basis(vec3(d), degree)
    theirs = dr.sh_eval(vec3(d), degree)
    ref = sh_basis_numpy(d, degree)
    assert len(ours) == len(theirs) == ref.shape[1] == (degree + 1) ** 2
    for i in range(len(ours)):
        a = np.broadcast_to(np.array(ours[i]), (257,))
        b = np.broadcast_to(np.array(theirs[i]), (257,))
        np.testing.assert_allclose(a, b, atol=2e-6)  # same basis, same order, same signs
        np.testing.assert_allclose(a, ref[:, i], atol=2e-6)


def test_basis_is_orthonormal():
    """Independent check of the constants: Gram matrix over the sphere (Gauss-Legendre x uniform phi) = identity."""
    ct, w = np.polynomial.legendre.leggauss(12)
    phi = np.arange(24) * (2 * np.pi / 24)
    st = np.sqrt(1 - ct ** 2)
    d = np.stack([np.outer(st, np.cos(phi)), np.outer(st, np.sin(phi)), np.outer(ct, np.ones_like(phi))], -1)
    weights = np.outer(w, np.full(24, 2 * np.pi / 24)).reshape(-1)
    b = sh_basis_numpy(d.reshape(-1, 3), 3)
    gram = (b * weights[:, None]).T @ b
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-12)


def test_basis_signs_match_reference():
    # reference computeColorFromSH: -C1*y*sh[1] + C1*z*sh[2] - C1*x*sh[3]
    b = sh_basis_numpy(np.eye(3), 1)
    assert b[0, 3] == -sh.SH_C1 and b[1, 1] == -sh.SH_C1 and b[2, 2] == sh.SH_C1


# ---------------------------------------------------------------------------------------------------- SH colours
def random_sh(n, degree, seed):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return rng.normal(size=(n, 3)).astype(np.float32) * 1.5, rng.normal(size=(n, k, 3)).astype(np.float32) * 0.5


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_eval_matches_numpy(degree):
    n = 500
    dc, rest = random_sh(n, degree, seed=degree)
    dirs = rand_dirs(n, seed=10 + degree, unit=False) * 5.0  # unnormalized: mean - camera centre
    got = sh.eval_sh_colors(vec3(dc), [vec3(rest[:, j]) for j in range(rest.shape[1])], vec3(dirs), degree)
    ref = eval_sh_numpy(dc, rest, dirs, degree)
    assert isinstance(got, mi.Vector3f)
    np.testing.assert_allclose(np3(got), ref, atol=1e-5)
    assert (ref == 0).any() and (ref > 0).any()  # both branches of the clamp are exercised


def test_active_degree_mask():
    n = 200
    dc, rest = random_sh(n, 3, seed=4)
    dirs = rand_dirs(n, seed=5)
    rest_v = [vec3(rest[:, j]) for j in range(15)]
    for active in range(4):
        got = np3(sh.eval_sh_colors(vec3(dc), rest_v, vec3(dirs), active))
        k = (active + 1) ** 2 - 1
        np.testing.assert_allclose(got, eval_sh_numpy(dc, rest[:, :k], dirs, active), atol=1e-5)
        np.testing.assert_allclose(got, eval_sh_numpy(dc, rest, dirs, active), atol=1e-5)
        if active < 3:
            assert not np.allclose(got, eval_sh_numpy(dc, rest, dirs, 3), atol=1e-3)
    with pytest.raises(ValueError, match="needs 8"):
        sh.eval_sh_colors(vec3(dc), rest_v[:3], vec3(dirs), 2)
    with pytest.raises(ValueError):
        sh.eval_sh_colors(vec3(dc), rest_v, vec3(dirs), 4)


def test_clamp_gradient_is_zero_where_clamped():
    dc_np = np.array([[3.0, -3.0, 0.1], [-5.0, 0.0, 5.0]], np.float32)  # C0 * dc + 0.5 < 0 for -3, -5
    dc = vec3(dc_np)
    dr.enable_grad(dc)
    out = sh.eval_sh_colors(dc, [], vec3(np.ones((2, 3))), 0)
    dr.backward(out.x + out.y + out.z)
    g = np3(dr.grad(dc))
    expect = np.where(sh.SH_C0 * dc_np + 0.5 < 0, 0.0, sh.SH_C0)
    np.testing.assert_allclose(g, expect, rtol=1e-6)
    assert np3(dr.detach(out))[0, 1] == 0.0


def test_gradient_through_direction_matches_finite_differences():
    n = 64
    dc, rest = random_sh(n, 3, seed=7)
    dc = dc * 0.1 + 1.0  # keep colours positive: no clamp kinks
    dirs_np = rand_dirs(n, seed=8, unit=False) * 3.0
    dirs = vec3(dirs_np)
    dr.enable_grad(dirs)
    out = sh.eval_sh_colors(vec3(dc), [vec3(rest[:, j]) for j in range(15)], dirs, 3)
    w = np.array([0.3, -0.7, 1.1])
    dr.backward(0.3 * out.x - 0.7 * out.y + 1.1 * out.z)  # Python floats: a NumPy scalar would give an object array
    g = np3(dr.grad(dirs))
    eps = 1e-5
    fd = np.zeros_like(dirs_np)
    for ax in range(3):
        e = np.zeros(3)
        e[ax] = eps
        fp = eval_sh_numpy(dc, rest, dirs_np + e, 3) @ w
        fm = eval_sh_numpy(dc, rest, dirs_np - e, 3) @ w
        fd[:, ax] = (fp - fm) / (2 * eps)
    np.testing.assert_allclose(g, fd, atol=2e-4, rtol=1e-3)


@pytest.mark.parametrize("degree", [1, 3])
def test_gather_from_model_tensors(degree):
    n = 50
    dc, rest = random_sh(n, 3, seed=degree)
    rng = np.random.default_rng(0)
    g = Gaussians.from_numpy(means=rng.normal(size=(n, 3)), scales=np.zeros((n, 3)), rotations=np.tile([1, 0, 0, 0], (n, 1)),
                             opacities=np.zeros(n), sh_dc=dc, sh_rest=rest)
    dirs = rand_dirs(n, seed=3)
    dr.enable_grad(g.sh_rest)
    dcv, restv = sh.gather_sh_coeffs(g.sh_dc, g.sh_rest, degree)
    assert len(restv) == (degree + 1) ** 2 - 1
    out = sh.eval_sh_colors(dcv, restv, vec3(dirs), degree)
    np.testing.assert_allclose(np3(dr.detach(out)), eval_sh_numpy(dc, rest, dirs, degree), atol=1e-5)
    dr.backward(dr.sum(out.x))
    grad = np.array(dr.grad(g.sh_rest)).reshape(n, 15, 3)
    k = (degree + 1) ** 2 - 1
    assert not grad[:, k:].any()            # inactive bands get no gradient
    unclamped = eval_sh_numpy(dc, rest, dirs, degree)[:, 0] > 0
    basis = sh_basis_numpy(dirs, degree)
    np.testing.assert_allclose(grad[:, :k, 0], basis[:, 1:] * unclamped[:, None], atol=1e-6)
    assert not grad[:, :, 1:].any()
    sel = dr.gather(mi.UInt32, mi.UInt32([4, 2]), mi.UInt32([0, 1]))
    dcs, _ = sh.gather_sh_coeffs(g.sh_dc, g.sh_rest, 0, index=sel)
    np.testing.assert_array_equal(np3(dcs), dc[[4, 2]])


def test_sh_module_avoids_float_min_max():
    # dr.minimum / dr.maximum / dr.clip on floats abort the process with libLLVM 15: the clamp must use dr.select
    tree = ast.parse(inspect.getsource(sh))
    used = {node.attr for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "dr"}
    assert not used & {"minimum", "maximum", "clip", "clamp"}
    assert "select" in used
