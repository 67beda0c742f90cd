"""``benchmarks/scene_blender.py --colmap``: a scene's rig written as a COLMAP-layout dataset (issue 53's stand-in for
a 400x400 table scene, so that code which cannot train on a scene file trains on the same views and points). Checked
against the scene dataset it is written from: the images composited over white, the poses, the points, and the
loader's hold-out (every 8th name) holding the rig's held-out views."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def test_a_scene_written_as_colmap_loads_with_its_views_poses_points_and_hold_out(tmp_path):
    from mi_gaussians.config import SceneConfig
    from mi_gaussians.data.dataset import load_dataset
    from mi_gaussians.data.images import read_image
    from mi_gaussians.data.scene_dataset import load_scene_dataset

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from scene_blender import main as write_scene

    out, cache = tmp_path / "colmap", tmp_path / "references"
    # (points sampled on the shapes: 64-pixel views hold too few SIFT features to triangulate)
    args = ["objects", "--size", "64", "--views", "10", "--test-views", "2", "--spp", "4", "--colmap",
            "--init", "shapes", "--out", str(out), "--cache", str(cache)]
    assert write_scene(args) == 0
    cfg = SceneConfig(views=10, test_views=2, spp=4, resolution=(64, 64), init="shapes")
    scene = load_scene_dataset(ROOT / "scenes" / "objects.xml", cfg, cache_root=cache, background=(1.0, 1.0, 1.0),
                               progress=False)
    ds = load_dataset(out, background=(1.0, 1.0, 1.0))
    # 12 views: the 2 held out on names 0000 and 0008, the 10 training ones between them, in the rig's order
    assert [v.name for v in ds.test] == ["0000.png", "0008.png"] and len(ds.train) == 10
    by_name = {v.name: v for v in scene.views}
    order = ["test_000"] + [f"train_{k:03d}" for k in range(7)] + ["test_001"] + [f"train_{k:03d}" for k in (7, 8, 9)]
    for name, v in zip(order, sorted(ds.views, key=lambda v: v.name)):
        want = by_name[name]
        np.testing.assert_allclose(v.camera.world_to_camera, want.camera.world_to_camera, atol=1e-6)
        assert (v.camera.fx, v.camera.cx, v.camera.width) == (want.camera.fx, want.camera.cx, 64)
        # the scene's own reference over white, up to the 8-bit sRGB encoding (which clips the highlights above 1
        # that the scene's loader keeps); where the object covers part of a pixel the colour is composited in sRGB
        # (as mi_objects/colmap and NeRF-synthetic loaders do) rather than in linear RGB as the scene's loader does
        raw = read_image(want.image_path)
        alpha = raw[..., 3:4]
        straight = np.where(alpha > 0, raw[..., :3] / np.maximum(alpha, 1e-8), 0.0)
        srgb = np.where(straight <= 0.0031308, 12.92 * straight, 1.055 * np.clip(straight, 0.0031308, None) ** (1 / 2.4)
                        - 0.055)
        want_img = np.where((alpha > 0) & (alpha < 1), np.clip(srgb, 0, 1) * alpha + 1 - alpha,
                            np.clip(want.load_image(), 0.0, 1.0))
        np.testing.assert_allclose(v.load_image(), want_img, atol=2.5 / 255)
    np.testing.assert_allclose(ds.points_xyz, scene.points_xyz, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(ds.points_rgb, np.clip(scene.points_rgb, 0, 1), atol=0.5 / 255 + 1e-6)   # (8-bit)
    # written once: a second call leaves the folder as it is
    stamp = (out / "images" / "0000.png").stat().st_mtime_ns
    assert write_scene(args) == 0 and (out / "images" / "0000.png").stat().st_mtime_ns == stamp
