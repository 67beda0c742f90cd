"""Regenerate the tiny test scenes in this folder (deterministic): ``python tests/data/make_fixtures.py``.

tiny_colmap/   3 images 24x16 (PNG), one PINHOLE camera with an off-centre principal point, COLMAP text model whose
               2D observations are the exact projections of its 3D points.
tiny_blender/  NeRF-synthetic layout: transforms_train.json (2 frames, file_path without extension),
               transforms_test.json (1 frame), RGBA PNGs 24x16, fl_x/fl_y/cx/cy/w/h given, cx, cy off-centre.
tiny_ngp/      instant-ngp layout: transforms.json with OpenCV distortion (k1, k2, p1, p2), 5 frames of which one
               image (images/0003.png) is missing on purpose.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

HERE = Path(__file__).parent
W, H = 24, 16
FX, FY, CX, CY = 20.0, 20.0, 11.5, 7.25


def look_at_cv(origin, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera (4, 4), OpenCV axes, camera at ``origin`` looking at ``target``."""
    o, t, u = (np.asarray(v, float) for v in (origin, target, up))
    z = t - o
    z /= np.linalg.norm(z)
    x = np.cross(z, u)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])            # rows: camera axes in world space
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ o
    return w2c


def quat_wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def pattern(seed: int, alpha: bool) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = (rng.random((H, W, 4 if alpha else 3)) * 255).astype(np.uint8)
    if alpha:
        img[..., 3] = np.linspace(0, 255, W, dtype=np.uint8)[None, :]   # every alpha from 0 to 1 along x
    return img


def poses(n: int) -> list[np.ndarray]:
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        out.append(look_at_cv([3 * math.cos(a), 3 * math.sin(a), 1.2], [0.05, -0.02, 0.1]))
    return out


def make_colmap() -> None:
    root = HERE / "tiny_colmap"
    shutil.rmtree(root, ignore_errors=True)
    (root / "images").mkdir(parents=True)
    (root / "sparse" / "0").mkdir(parents=True)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.4, 0.4, (6, 3))
    cols = rng.integers(0, 256, (6, 3))
    names = ["a.png", "b.png", "c.png"]
    w2cs = poses(3)
    tracks = {j: [] for j in range(len(pts))}
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (name, w2c) in enumerate(zip(names, w2cs), start=1):
        Image.fromarray(pattern(i, alpha=False)).save(root / "images" / name)
        q, t = quat_wxyz(w2c[:3, :3]), w2c[:3, 3]
        lines.append(" ".join(f"{v:.17g}" for v in [i, *q, *t]) + f" 1 {name}")
        pc = pts @ w2c[:3, :3].T + t
        uv = np.c_[FX * pc[:, 0] / pc[:, 2] + CX, FY * pc[:, 1] / pc[:, 2] + CY]
        obs = []
        for j, (u, v) in enumerate(uv):
            tracks[j].append((i, len(obs)))
            obs.append(f"{u:.17g} {v:.17g} {j + 1}")
        lines.append(" ".join(obs))
    (root / "sparse" / "0" / "images.txt").write_text("\n".join(lines) + "\n")
    (root / "sparse" / "0" / "cameras.txt").write_text(
        "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + f"1 PINHOLE {W} {H} {FX} {FY} {CX} {CY}\n")
    p_lines = ["# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for j, (p, c) in enumerate(zip(pts, cols)):
        track = " ".join(f"{i} {k}" for i, k in tracks[j])
        p_lines.append(f"{j + 1} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} {c[0]} {c[1]} {c[2]} 0 {track}")
    (root / "sparse" / "0" / "points3D.txt").write_text("\n".join(p_lines) + "\n")


def frame(file_path: str, w2c: np.ndarray) -> dict:
    c2w_gl = np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])
    return {"file_path": file_path, "transform_matrix": c2w_gl.tolist()}


def make_blender() -> None:
    root = HERE / "tiny_blender"
    shutil.rmtree(root, ignore_errors=True)
    (root / "train").mkdir(parents=True)
    (root / "test").mkdir()
    w2cs = poses(3)
    common = {"camera_angle_x": 2 * math.atan(W / (2 * FX)), "fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY,
              "w": W, "h": H}
    for split, idx in (("train", [0, 1]), ("test", [2])):
        frames = []
        for k, i in enumerate(idx):
            Image.fromarray(pattern(10 + i, alpha=True), mode="RGBA").save(root / split / f"r_{k}.png")
            frames.append(frame(f"./{split}/r_{k}", w2cs[i]))
        (root / f"transforms_{split}.json").write_text(json.dumps({**common, "frames": frames}, indent=1))


def make_ngp() -> None:
    root = HERE / "tiny_ngp"
    shutil.rmtree(root, ignore_errors=True)
    (root / "images").mkdir(parents=True)
    w2cs = poses(5)
    meta = {"fl_x": FX, "fl_y": FY * 1.0005, "cx": CX, "cy": CY, "w": float(W), "h": float(H),
            "k1": 0.05, "k2": -0.02, "p1": 0.001, "p2": -0.0005, "aabb_scale": 4, "frames": []}
    for i, w2c in enumerate(w2cs):
        name = f"images/{i:04d}.png"
        if i != 3:
            Image.fromarray(pattern(20 + i, alpha=False)).save(root / name)
        meta["frames"].append(frame(name, w2c))
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))


if __name__ == "__main__":
    make_colmap()
    make_blender()
    make_ngp()
    print(f"wrote tiny_colmap, tiny_blender, tiny_ngp under {HERE}")
