"""Changes of frame of a model's raw parameters (NumPy dicts keyed by ``PARAMETER_NAMES``), for the file formats
that store Gaussians in another frame than the model's: axis flips (``.spz``'s RUB frame, glTF's LUF frame) and the
affine transform of a glTF node.

The model's frame is that of a 3DGS PLY, which the ecosystem reads as RDF (x right, y down, z forward: COLMAP's and
OpenCV's camera axes, nianticlabs/spz's ``CoordinateSystem::RDF``, "PLY coordinate system"). A rigid change of frame
``x' = M x`` moves the means, turns each Gaussian (``R' = M R``, or ``D R D`` for a diagonal flip ``D``, which keeps
the quaternion's real part) and turns the view-dependent colour: the SH coefficients of band ``l`` mix among
themselves so that the colour seen along ``d' = M d`` is the old colour along ``d``.

The SH basis here is the reference's (``computeColorFromSH``, the same as :mod:`mi_gaussians.model.sh` and as
KHR_gaussian_splatting's appendix, Condon-Shortley phase included), in NumPy.
"""

from __future__ import annotations

import numpy as np

from ..conventions import sh_degree_from_coeff_count

#: Per higher-band SH basis function (degree 1, 2, 3 in the reference's order), whether it is odd in x, y and z.
#: Every basis function of the reference's real SH has a definite parity in each axis (y, z, x; xy, yz, 2z^2-x^2-y^2,
#: xz, x^2-y^2; y(3x^2-y^2), xyz, y(4z^2-x^2-y^2), z(2z^2-3x^2-3y^2), x(4z^2-x^2-y^2), z(x^2-y^2), x(x^2-3y^2)).
SH_PARITY = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0],
                      [1, 1, 0], [0, 1, 1], [0, 0, 0], [1, 0, 1], [0, 0, 0],
                      [0, 1, 0], [1, 1, 1], [0, 1, 0], [0, 0, 1], [1, 0, 0], [0, 0, 1], [1, 0, 0]], np.int64)

_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
       1.445305721320277, -0.5900435899266435)


def sh_flip_signs(signs) -> np.ndarray:
    """(15,) sign of each higher-band SH coefficient under the axis flip ``diag(signs)`` (each of ``signs`` +-1)."""
    s = np.asarray(signs, np.float64)
    return np.prod(np.where(SH_PARITY == 1, s[None, :], 1.0), axis=1)


def flip_axes(p: dict, signs) -> dict:
    """``p`` in the frame ``x' = diag(signs) x`` (each of ``signs`` +-1; an odd number of -1 mirrors, and the
    Gaussians are mirrored with it). Quaternions stay quaternions: the flip ``D`` turns ``R`` into ``D R D``, whose
    quaternion is ``(w, det(D) * D (x, y, z))`` (the same covariance as ``D R``, without changing ``w``)."""
    d = np.asarray(signs, np.float64)
    det = float(np.prod(d))
    q = np.asarray(p["rotations"], np.float64) * np.concatenate([[1.0], d * det])
    sh_rest = np.asarray(p["sh_rest"], np.float64)
    return {**p, "means": (np.asarray(p["means"], np.float64) * d).astype(np.float32),
            "rotations": q.astype(np.float32),
            "sh_rest": (sh_rest * sh_flip_signs(d)[: sh_rest.shape[1], None]).astype(np.float32)}


# ---------------------------------------------------------------------------------------------------- SH basis
def sh_basis(dirs, degree: int) -> np.ndarray:
    """(N, (degree + 1)^2) real SH basis of the reference at the unit directions ``dirs`` (N, 3), DC first."""
    d = np.asarray(dirs, np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = [np.full_like(x, 0.28209479177387814)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [_C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy), _C2[3] * x * z, _C2[4] * (xx - yy)]
    if degree >= 3:
        out += [_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4 * zz - xx - yy),
                _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy), _C3[5] * z * (xx - yy),
                _C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=1)


def _sample_directions(n: int = 64) -> np.ndarray:
    """``n`` unit directions spread over the sphere (a Fibonacci lattice: fixed, no randomness)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sh_rotation(rot: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per band ``l`` = 1..degree, the (2l+1, 2l+1) matrix ``W`` such that coefficients ``W k`` seen along ``rot d``
    give the colour that ``k`` gave along ``d`` (``rot`` a 3x3 rotation). Solved by least squares on 64 directions:
    exact, as each band is closed under rotations."""
    dirs = _sample_directions()
    new = sh_basis(dirs, degree)                       # Y(d')
    old = sh_basis(dirs @ np.asarray(rot, np.float64), degree)    # Y(rot^T d'): rows are d'^T rot
    out = []
    for l in range(1, degree + 1):
        band = slice(l * l, (l + 1) * (l + 1))
        out.append(np.linalg.lstsq(new[:, band], old[:, band], rcond=None)[0])
    return out


def rotate_sh(sh_rest: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """``sh_rest`` (N, K - 1, 3) of Gaussians turned by the rotation ``rot`` (3x3)."""
    sh_rest = np.asarray(sh_rest, np.float64)
    degree = sh_degree_from_coeff_count(sh_rest.shape[1] + 1)
    out = np.empty_like(sh_rest)
    for l, w in enumerate(sh_rotation(rot, degree), start=1):
        band = slice(l * l - 1, (l + 1) * (l + 1) - 1)
        out[:, band] = np.einsum("ij,njc->nic", w, sh_rest[:, band])
    return out


# ---------------------------------------------------------------------------------------------------- quaternions
def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a b`` of (..., 4) ``(w, x, y, z)`` quaternions."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) ``(w, x, y, z)`` quaternions (normalized here) -> (N, 3, 3) rotation matrices."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1).reshape(-1, 3, 3)


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N, 4) unit ``(w, x, y, z)`` quaternions (Shepperd: the largest of the four
    diagonal combinations picks the stable formula)."""
    m = np.asarray(m, np.float64).reshape(-1, 3, 3)
    t = np.stack([m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2], m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                  -m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], -m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], axis=1)
    k = np.argmax(t, axis=1)
    r = np.sqrt(np.maximum(1.0 + t[np.arange(len(m)), k], 1e-300))
    s = 0.5 / r
    q = np.empty((len(m), 4))
    c = [m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1],   # 4w x, 4w y, 4w z
         m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]]   # 4xy, 4xz, 4yz
    cand = [np.stack([0.5 * r, c[0] * s, c[1] * s, c[2] * s], 1), np.stack([c[0] * s, 0.5 * r, c[3] * s, c[4] * s], 1),
            np.stack([c[1] * s, c[3] * s, 0.5 * r, c[5] * s], 1), np.stack([c[2] * s, c[4] * s, c[5] * s, 0.5 * r], 1)]
    for i in range(4):
        q[k == i] = cand[i][k == i]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------------- transforms
def transform(p: dict, m: np.ndarray, t=(0.0, 0.0, 0.0)) -> dict:
    """``p`` moved by the affine map ``x -> m x + t`` (``m`` 3x3 with a positive determinant): means, covariances
    ``m S m^T`` and, by the rotation of ``m``'s polar decomposition, the SH. A rotation times a uniform scale keeps each
    Gaussian's axes (``q' = q_m q``, log scales + log s); any other ``m`` re-derives axes and scales from the
    covariance."""
    m = np.asarray(m, np.float64)
    if not np.linalg.det(m) > 0:
        raise ValueError("the transform mirrors or flattens (its determinant is not positive)")
    u, sv, vt = np.linalg.svd(m)
    rot = u @ vt                                            # the rotation of the polar decomposition
    means = np.asarray(p["means"], np.float64) @ m.T + np.asarray(t, np.float64)
    q = np.asarray(p["rotations"], np.float64)
    scales = np.asarray(p["scales"], np.float64)
    if np.ptp(sv) <= 1e-6 * sv.max():                      # similarity: rot times a uniform scale
        q = quat_multiply(matrix_to_quat(rot[None])[0], q)
        scales = scales + np.log(sv.mean())
    else:
        a = m @ quat_to_matrix(q) * np.exp(scales)[:, None, :]           # m R S
        var, axes = np.linalg.eigh(a @ np.transpose(a, (0, 2, 1)))
        axes[np.linalg.det(axes) < 0, :, 0] *= -1                        # a rotation, not a reflection
        q = matrix_to_quat(axes)
        scales = 0.5 * np.log(np.maximum(var, 1e-300))
    sh_rest = np.asarray(p["sh_rest"], np.float64)
    if sh_rest.shape[1]:
        sh_rest = rotate_sh(sh_rest, rot)
    return {**p, "means": means.astype(np.float32), "rotations": q.astype(np.float32),
            "scales": scales.astype(np.float32), "sh_rest": sh_rest.astype(np.float32)}
