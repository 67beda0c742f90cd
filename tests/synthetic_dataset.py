"""A small Blender/NeRF-layout dataset made on the fly: the shipped ``scenes/tiny_gaussians.ply`` rendered from a
ring of cameras (RGBA PNGs, transforms_train/test.json). Used by the training tests; nothing is downloaded."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

import mi_gaussians as mig

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def look_at_c2w_gl(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    upv = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, upv, back, eye
    return c2w


def make_blender_dataset(root: Path, n_train: int = 16, n_test: int = 4, size: int = 64, radius: float = 3.4,
                         seed: int = 0) -> Path:
    from PIL import Image

    g = mig.Gaussians.load_ply(SCENES / "tiny_gaussians.ply")
    fov = math.radians(45.0)
    f = 0.5 * size / math.tan(fov / 2)
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    for split, n in (("train", n_train), ("test", n_test)):
        (root / split).mkdir(exist_ok=True)
        frames = []
        for i in range(n):
            az = rng.uniform(0, 2 * math.pi)
            el = rng.uniform(math.radians(10), math.radians(60))
            eye = radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            c2w = look_at_c2w_gl(eye)
            cam = mig.Camera.from_camera_to_world_gl(c2w, size, size, f, f, size / 2, size / 2)
            out = mig.render(g, cam)
            rgb = np.array(out.rgb)
            a = np.array(out.alpha)[..., None]
            straight = np.where(a > 1e-6, rgb / np.maximum(a, 1e-6), 0.0)      # un-premultiplied colour
            rgba = np.concatenate([np.clip(straight, 0, 1), np.clip(a, 0, 1)], axis=-1)
            Image.fromarray((rgba * 255 + 0.5).astype(np.uint8), "RGBA").save(root / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    return root
