"""Generate ``scenes/tiny_gaussians.ply``: a small procedural 3DGS model (no data needed), and its camera JSON.

A ring of coloured, anisotropic Gaussians around a textured sphere of small ones, SH degree 1 with a view-dependent
tint. Deterministic (seeded). Run: ``python scenes/make_tiny_gaussians.py`` (writes next to this file).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

C0 = 0.28209479177387814


def make(seed: int = 0):
    rng = np.random.default_rng(seed)
    # sphere shell of small Gaussians with a checker-like colour pattern
    n_s = 1500
    v = rng.normal(size=(n_s, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    theta, phi = np.arctan2(v[:, 1], v[:, 0]), np.arccos(np.clip(v[:, 2], -1, 1))
    checker = ((np.floor(theta / (math.pi / 6)) + np.floor(phi / (math.pi / 6))) % 2)[:, None]
    col_s = checker * np.array([0.9, 0.75, 0.2]) + (1 - checker) * np.array([0.15, 0.3, 0.8])
    means_s = 0.6 * v
    scales_s = np.log(np.full((n_s, 3), 0.045)) + rng.normal(0, 0.1, (n_s, 3))
    # ring of elongated Gaussians
    n_r = 500
    a = rng.uniform(0, 2 * math.pi, n_r)
    means_r = np.stack([1.1 * np.cos(a), 1.1 * np.sin(a), rng.normal(0, 0.03, n_r)], axis=1)
    col_r = np.stack([0.5 + 0.5 * np.cos(a), 0.5 + 0.5 * np.cos(a + 2.1), 0.5 + 0.5 * np.cos(a + 4.2)], axis=1)
    scales_r = np.log(np.stack([np.full(n_r, 0.09), np.full(n_r, 0.02), np.full(n_r, 0.02)], axis=1))
    # rotate each ring Gaussian so its long axis follows the ring tangent (rotation about z by a + pi/2)
    half = (a + math.pi / 2) / 2
    rot_r = np.stack([np.cos(half), np.zeros(n_r), np.zeros(n_r), np.sin(half)], axis=1)
    rot_s = rng.normal(size=(n_s, 4))
    means = np.concatenate([means_s, means_r])
    rgb = np.concatenate([col_s, col_r])
    n = len(means)
    sh_rest = np.zeros((n, 3, 3))
    sh_rest[:, 2, :] = rng.normal(0, 0.15, (n, 3))        # a view-dependent tint (band 1, m = +1: -C1 x)
    return dict(means=means, scales=np.concatenate([scales_s, scales_r]), rotations=np.concatenate([rot_s, rot_r]),
                opacities=np.concatenate([np.full(n_s, 2.5), np.full(n_r, 1.5)]),
                sh_dc=(rgb - 0.5) / C0, sh_rest=sh_rest)


def camera(width=320, height=240):
    """Looking at the origin from (0, -3.2, 1.2), z up, OpenCV axes."""
    eye, target, up = np.array([0.0, -3.2, 1.2]), np.zeros(3), np.array([0.0, 0.0, 1.0])
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    f = 0.5 * width / math.tan(math.radians(40) / 2)
    return {"width": width, "height": height, "fx": f, "fy": f, "cx": width / 2 + 7.5, "cy": height / 2 - 4.25,
            "world_to_camera": w2c.tolist(), "name": "tiny_gaussians"}


def main(out_dir: Path) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from mi_gaussians.model.ply import write_ply

    write_ply(out_dir / "tiny_gaussians.ply", **{k: v.astype(np.float32) for k, v in make().items()})
    (out_dir / "tiny_gaussians_camera.json").write_text(json.dumps(camera(), indent=2) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent)
