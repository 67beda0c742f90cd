"""A Mitsuba scene's camera rig written as a Blender-layout (NeRF-synthetic) or COLMAP-layout dataset, so that it
trains like any capture: without the scene's shapes, from triangulated or random points.

    python benchmarks/scene_blender.py objects --rig sphere --size 200 --views 100 --test-views 20 \
        --out /tmp/objects_sphere                   # an object seen from every side, RGBA PNGs (issue 52's scene)
    python benchmarks/scene_blender.py room --out /tmp/room_blender --no-alpha
    python benchmarks/scene_blender.py objects --size 400 --spp 32 --colmap --out /tmp/objects_colmap
                                                    # COLMAP layout: the views composited over white, the points
                                                    # triangulated from the training views (--init triangulate's)

The references are path-traced by ``mi-gs optimize``'s own code (``load_scene_dataset``: the rig, seeds and cache of
``scenes/<name>.xml``; ``--cache`` is shared with other benchmarks). Images are 8-bit sRGB PNGs; with alpha (the
default) they hold straight colour and Mitsuba's coverage alpha, as NeRF-synthetic's do (the scene must hide its
emitters for the background to be empty), without it the references composited over black.
``transforms_train.json`` / ``transforms_test.json`` hold OpenGL camera-to-world matrices and ``camera_angle_x``.
The COLMAP layout (as ``../shared/data/mi_objects/colmap``) holds ``images/`` (RGB PNGs, straight colour composited
over white in 8-bit sRGB) and a text model in ``sparse/0`` (one PINHOLE camera, the poses, the triangulated points
without tracks); its views are numbered so that the loader's hold-out (every 8th) is the rig's held-out views, plus the
training views that fall on the 8th places left over.
Code that cannot train on a scene file (an earlier version) trains on it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _reference(path: Path) -> tuple:
    """A cached reference render: (linear RGB premultiplied by Mitsuba's alpha as read, its straight colour, alpha)."""
    from mi_gaussians.data.images import read_image

    ref = read_image(path)
    a = ref[..., 3:4] if ref.shape[2] == 4 else np.ones_like(ref[..., :1])
    return ref, np.where(a > 0, ref[..., :3] / np.maximum(a, 1e-8), 0.0), a


def write_dataset(scene: Path, out: Path, cache: Path, scene_cfg=None, alpha: bool = True) -> Path:
    """Write ``scene``'s training and held-out views as a Blender-layout dataset in ``out`` (once: an existing
    ``transforms_test.json`` means it is written already). ``scene_cfg``: the rig (a ``SceneConfig``)."""
    if (out / "transforms_test.json").is_file():
        return out
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from PIL import Image

    from mi_gaussians.config import SceneConfig
    from mi_gaussians.data.camera import GL_TO_CV
    from mi_gaussians.data.scene_dataset import load_scene_dataset
    from mi_gaussians.imwrite import linear_to_srgb, to_uint8

    cfg = dataclasses.replace(scene_cfg or SceneConfig(), init="random", init_points=1)
    ds = load_scene_dataset(scene, cfg, cache_root=cache, log=lambda s: print(s, file=sys.stderr))
    for split, views in (("train", ds.train), ("test", ds.test)):
        frames = []
        (out / split).mkdir(parents=True, exist_ok=True)
        for v in views:
            c = v.camera
            if abs(c.fx - c.fy) > 1e-6 * c.fx or abs(c.cx - c.width / 2) > 1e-6 or abs(c.cy - c.height / 2) > 1e-6:
                raise SystemExit(f"camera {c.name}: the Blender layout needs square pixels and a centred image")
            ref, straight, a = _reference(v.image_path)
            if alpha:
                img = np.concatenate([linear_to_srgb(np.clip(straight, 0, 1)), a], axis=2)
            else:
                img = linear_to_srgb(np.clip(ref[..., :3], 0, 1))
            Image.fromarray(to_uint8(np.clip(img, 0, 1))).save(out / split / f"{v.name}.png")
            c2w = np.linalg.inv(c.world_to_camera) @ GL_TO_CV
            frames.append({"file_path": f"./{split}/{v.name}", "transform_matrix": c2w.tolist()})
        fov = 2 * math.atan(views[0].camera.width / (2 * views[0].camera.fx))
        (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}, indent=1))
    return out


def write_colmap(scene: Path, out: Path, cache: Path, scene_cfg=None) -> Path:
    """Write ``scene``'s views over white and its initial points (``scene_cfg.init``: triangulated by default) as a
    COLMAP-layout dataset in ``out`` (once: an existing ``sparse/0/points3D.txt`` means it is written already)."""
    if (out / "sparse" / "0" / "points3D.txt").is_file():
        return out
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from PIL import Image

    from mi_gaussians.config import DataConfig, SceneConfig
    from mi_gaussians.data.colmap import images_text
    from mi_gaussians.data.scene_dataset import load_scene_dataset
    from mi_gaussians.imwrite import linear_to_srgb, to_uint8

    cfg = scene_cfg or SceneConfig(init="triangulate")
    ds = load_scene_dataset(scene, cfg, cache_root=cache, background=(1.0, 1.0, 1.0),
                            log=lambda s: print(s, file=sys.stderr))
    # the held-out views where the COLMAP loader holds out (every 8th by name), the training views between them
    every = DataConfig().test_every
    train, test = list(ds.train), list(ds.test)
    views = [test.pop(0) if i % every == 0 and test else train.pop(0) for i in range(len(ds.views))]
    if test:
        raise SystemExit(f"{scene}: more held-out views ({len(ds.test)}) than every {every}th place can hold")
    moved = [v.name for i, v in enumerate(views) if i % every == 0 and v.name.startswith("train")]
    if moved:
        print(f"held out in the COLMAP layout, with the rig's {len(ds.test)}: {', '.join(moved)}", file=sys.stderr)
    c0 = views[0].camera
    if any((v.camera.width, v.camera.height, v.camera.fx, v.camera.fy, v.camera.cx, v.camera.cy)
           != (c0.width, c0.height, c0.fx, c0.fy, c0.cx, c0.cy) for v in views):
        raise SystemExit(f"{scene}: the COLMAP layout written here has one camera for all views")
    (out / "images").mkdir(parents=True, exist_ok=True)
    model = out / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    names = []
    for i, v in enumerate(views):
        _, straight, a = _reference(v.image_path)
        srgb = to_uint8(linear_to_srgb(np.clip(straight, 0, 1))).astype(np.float64) / 255.0
        a8 = to_uint8(np.clip(a, 0, 1)).astype(np.float64) / 255.0
        names.append(f"{i:04d}.png")
        Image.fromarray(to_uint8(srgb * a8 + (1.0 - a8))).save(out / "images" / names[-1])
    (model / "cameras.txt").write_text(
        f"1 PINHOLE {c0.width} {c0.height} {c0.fx!r} {c0.fy!r} {c0.cx!r} {c0.cy!r}\n")
    (model / "images.txt").write_text(images_text(names, [v.camera.world_to_camera for v in views], [1] * len(names)))
    rgb8 = np.clip(np.round(np.asarray(ds.points_rgb, np.float64) * 255.0), 0, 255).astype(int)
    (model / "points3D.txt").write_text("".join(
        f"{k + 1} {x!r} {y!r} {z!r} {r} {g} {b} 0\n"
        for k, ((x, y, z), (r, g, b)) in enumerate(zip(np.asarray(ds.points_xyz, np.float64).tolist(), rgb8.tolist()))))
    return out


def main(argv=None) -> int:
    from mi_gaussians.config import SceneConfig

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("name", help="scenes/<name>.xml")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--rig", default="auto", help="the scene rig (SceneConfig.rig): auto, sensors, hemisphere, sphere")
    ap.add_argument("--size", type=int, default=None, help="film width and height in pixels (default: the scene's)")
    ap.add_argument("--views", type=int, default=SceneConfig().views)
    ap.add_argument("--test-views", type=int, default=SceneConfig().test_views)
    ap.add_argument("--spp", type=int, default=None)
    ap.add_argument("--no-alpha", action="store_true", help="RGB PNGs composited over black")
    ap.add_argument("--colmap", action="store_true", help="a COLMAP layout (views over white, triangulated points)")
    ap.add_argument("--init", default="triangulate",
                    help="the COLMAP layout's points (SceneConfig.init: triangulate, shapes, ...; default triangulate)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/mi_gs_scene_blender/references"))
    args = ap.parse_args(argv)
    cfg = SceneConfig(rig=args.rig, views=args.views, test_views=args.test_views, spp=args.spp,
                      resolution=None if args.size is None else (args.size, args.size), init=args.init)
    scene = ROOT / "scenes" / f"{args.name}.xml"
    if args.colmap:
        write_colmap(scene, args.out, args.cache, cfg)
    else:
        write_dataset(scene, args.out, args.cache, cfg, alpha=not args.no_alpha)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
