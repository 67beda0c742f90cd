"""Known pose errors, to measure pose optimisation (``--set data.pose_noise=DEG,FRAC``, gsplat's ``pose_noise``), and
the distance between two sets of poses.

:func:`perturbed_views` turns every training camera by exactly ``DEG`` degrees about a uniformly random axis through
its centre and moves its centre by exactly ``FRAC`` times the scene extent in a uniformly random direction, seeded, so
that a run and its evaluation draw the same errors. (gsplat draws its perturbation's 9 numbers from one normal
distribution; fixed sizes make "the error before" a setting rather than a sample.) :func:`pose_errors` gives the mean
rotation error (degrees, the angle of ``R_a R_b^T``) and the mean distance between the centres;
:func:`reprojection_error` what the image sees of the difference: how far the scene's points land from where the true
camera puts them, in pixels. The two tell different things: a small sideways move of a camera and a small turn shift
the image of a distant object alike, so a correction can trade one for the other (angles and centres off, the image
right) where the scene's depth range is small against its distance.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .camera import Camera
from .dataset import Dataset

# the random stream of the perturbation, apart from every other stream seeded by data.seed
_STREAM = 0x9053


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """The (3, 3) rotation by ``angle`` radians about the unit vector ``axis`` (Rodrigues)."""
    k = np.asarray(axis, np.float64)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def perturbed_cameras(cameras: list[Camera], degrees: float, distance: float, seed: int) -> list[Camera]:
    """``cameras``, each turned by ``degrees`` about a random axis through its centre and its centre moved by
    ``distance`` (world units) in a random direction (seeded)."""
    rng = np.random.default_rng([int(seed), _STREAM])
    axes, moves = _unit_vectors(rng, len(cameras)), _unit_vectors(rng, len(cameras)) * float(distance)
    out = []
    for cam, axis, move in zip(cameras, axes, moves):
        w2c = cam.world_to_camera
        R = w2c[:3, :3] @ rotation_about(axis, math.radians(degrees)).T    # camera axes turned about the world axis
        centre = cam.center + move
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = R, -R @ centre
        out.append(dataclasses.replace(cam, world_to_camera=m))
    return out


def perturbed_views(ds: Dataset, noise: tuple[float, float], seed: int) -> Dataset:
    """``ds`` with its training cameras perturbed by ``noise`` = (degrees, fraction of the scene extent) (module
    docstring); the test cameras, the points and everything else as they were. No noise: ``ds`` itself."""
    degrees, fraction = (float(x) for x in noise)
    if degrees == 0 and fraction == 0:
        return ds
    cams = perturbed_cameras([v.camera for v in ds.train], degrees, fraction * ds.extent, seed)
    return dataclasses.replace(ds, train=[dataclasses.replace(v, camera=c) for v, c in zip(ds.train, cams)])


def pose_errors(cameras: list[Camera], truth: list[Camera]) -> tuple[float, float]:
    """(mean rotation error in degrees, mean distance between the centres) of ``cameras`` against ``truth``."""
    angles, distances = [], []
    for a, b in zip(cameras, truth):
        rel = a.world_to_camera[:3, :3] @ b.world_to_camera[:3, :3].T
        # (atan2 of the sine and cosine of the angle: exact for small angles too, where acos of the cosine is not)
        sine = 0.5 * math.hypot(rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1])
        angles.append(math.degrees(math.atan2(sine, (np.trace(rel) - 1.0) / 2.0)))
        distances.append(float(np.linalg.norm(a.center - b.center)))
    return float(np.mean(angles)) if angles else 0.0, float(np.mean(distances)) if distances else 0.0


# the reprojection error projects at most this many points (an evenly strided subset, :func:`reprojection_points`):
# enough for a mean, a fraction of a second for a hundred cameras
MAX_REPROJECTED_POINTS = 20_000


def reprojection_points(points: np.ndarray | None, max_points: int = MAX_REPROJECTED_POINTS) -> np.ndarray | None:
    """``points`` (N, 3) as float64, or an evenly strided subset of at most ``max_points`` of them."""
    if points is None:
        return None
    return np.asarray(points, np.float64)[::max(1, -(-len(points) // max_points))]


def reprojection_error(cameras: list[Camera], truth: list[Camera], points: np.ndarray,
                       max_points: int = MAX_REPROJECTED_POINTS) -> float | None:
    """The mean over cameras of the mean distance in pixels between where ``cameras[i]`` and ``truth[i]`` project
    ``points`` (N, 3), over the points in front of both that the true camera sees inside its image; None without
    points or where no camera sees any. Of more than ``max_points`` points, :func:`reprojection_points`' subset."""
    points = reprojection_points(points, max_points)
    if points is None or len(points) == 0:
        return None
    means = []
    for a, b in zip(cameras, truth):
        uv_a, z_a = a.project(points)
        uv_b, z_b = b.project(points)
        seen = (z_a > 0) & b.sees(uv_b, z_b)
        if seen.any():
            means.append(float(np.mean(np.linalg.norm(uv_a[seen] - uv_b[seen], axis=1))))
    return float(np.mean(means)) if means else None
