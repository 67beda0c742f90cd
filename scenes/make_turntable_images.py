"""Render ``scenes/turntable_images/``: a small image set for ``mi-gs convert`` (structure from motion with pycolmap).

A textured tabletop with a few objects, seen from an arc of cameras around it (16 views over 165 degrees). The textures are seeded random
multi-scale noise with coloured blobs, so SIFT finds many distinctive features; the poses are NOT shipped (the point
of the set is to recover them).

    python scenes/make_turntable_images.py            # writes scenes/turntable_images/view_XX.jpg

Deterministic for a given Mitsuba version (fixed texture seed and render seeds).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

N_VIEWS = 16
RESOLUTION = 200
SPP = 64
RADIUS = 3.3
ARC_DEG = 165.0
FOV_DEG = 50.0


def noise_texture(seed: int, size: int = 512) -> np.ndarray:
    """(size, size, 3) float32 in [0, 1]: high-contrast multi-octave colour noise with random disks and squares."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    img = np.zeros((size, size, 3), np.float32)
    for octave, amp in zip((4, 8, 16, 32), (1.0, 0.8, 0.6, 0.4)):
        g = rng.random((octave, octave, 3)).astype(np.float32)
        img += amp * np.stack([np.asarray(Image.fromarray(g[..., c], mode="F")
                                          .resize((size, size), Image.Resampling.BICUBIC)) for c in range(3)], 2)
    img = (img - img.min(axis=(0, 1))) / (img.max(axis=(0, 1)) - img.min(axis=(0, 1)))
    yy, xx = np.mgrid[0:size, 0:size]
    for _ in range(700):
        cx, cy, r = rng.integers(0, size), rng.integers(0, size), rng.integers(4, 14)
        shape = ((xx - cx) ** 2 + (yy - cy) ** 2 < r * r) if rng.random() < 0.5 else \
            ((np.abs(xx - cx) < r) & (np.abs(yy - cy) < r))
        img[shape] = rng.random(3) ** 2
    return (0.05 + 0.75 * np.clip(img, 0, 1)).astype(np.float32)


def scene_dict(mi) -> dict:
    def tex(seed):
        return {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(noise_texture(seed)),
                                                   "raw": False, "filter_type": "bilinear"}}

    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 4, "bsdf_samples": 1},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.35}},
        "sun": {"type": "directional", "direction": [-0.4, -0.3, -1.0], "irradiance": {"type": "rgb", "value": 1.3}},
        "table": {"type": "rectangle", "to_world": T().scale([1.6, 1.6, 1.0]), "bsdf": tex(1)},
        "cube": {"type": "cube", "to_world": T().translate([-0.45, 0.3, 0.35]) @ T().rotate([0, 0, 1], 25)
                 @ T().scale(0.35), "bsdf": tex(2)},
        "ball": {"type": "sphere", "center": [0.5, 0.25, 0.4], "radius": 0.4, "bsdf": tex(3)},
        "post": {"type": "cylinder", "p0": [0.1, -0.6, 0.0], "p1": [0.1, -0.6, 0.9], "radius": 0.22, "bsdf": tex(4)},
        "cap": {"type": "disk", "to_world": T().translate([0.1, -0.6, 0.9]) @ T().scale(0.22), "bsdf": tex(5)},
    }


def camera_to_world(mi, k: int):
    azimuth = math.radians(-80.0 + ARC_DEG * k / (N_VIEWS - 1))     # an arc: neighbours ~11 degrees apart
    elevation = math.radians(32.0 + 8.0 * math.sin(2.5 * azimuth))   # a little vertical variation
    origin = [RADIUS * math.cos(elevation) * math.cos(azimuth), RADIUS * math.cos(elevation) * math.sin(azimuth),
              RADIUS * math.sin(elevation)]
    return mi.ScalarTransform4f().look_at(origin=origin, target=[0.0, 0.0, 0.3], up=[0.0, 0.0, 1.0])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "turntable_images")
    ap.add_argument("--variant", default="scalar_rgb")
    ap.add_argument("--spp", type=int, default=SPP)
    args = ap.parse_args(argv)

    import mitsuba as mi
    from PIL import Image

    mi.set_variant(args.variant)
    scene = mi.load_dict(scene_dict(mi))
    args.out.mkdir(parents=True, exist_ok=True)
    for k in range(N_VIEWS):
        sensor = mi.load_dict({
            "type": "perspective", "fov": FOV_DEG, "to_world": camera_to_world(mi, k),
            "film": {"type": "hdrfilm", "width": RESOLUTION, "height": RESOLUTION, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": args.spp},
        })
        img = mi.render(scene, sensor=sensor, seed=k)
        srgb = np.array(mi.Bitmap(img).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True))
        Image.fromarray(srgb).save(args.out / f"view_{k:02d}.jpg", quality=92)
        print(f"wrote {args.out / f'view_{k:02d}.jpg'}")


if __name__ == "__main__":
    main()
