"""Random initialization benchmark: Blender-layout scenes (no SfM points) trained from the reference's cube
(``--set data.random_init=cube``, the default) and from the frustum sampler (``data.random_init=frustum``), in the same
run with the same seed: PSNR / SSIM on the held-out views and the final count.

    python benchmarks/init.py                                  # mi_objects/blender and room_blender, 3k iterations
    python benchmarks/init.py --datasets room_blender --iterations 7000

Datasets:
  * mi_objects_blender: ../shared/data/mi_objects/blender (objects inside the reference's [-1.3, 1.3]^3 cube), white
    background;
  * room_blender: scenes/room.xml's 32 declared cameras inside a 4 x 2.6 x 4 room, path-traced by Mitsuba (the rig and
    reference code of ``mi-gs optimize scenes/room.xml``) and written in the Blender layout (sRGB PNGs,
    transforms_train.json / transforms_test.json with every 8th camera held out), so that it trains like any Blender
    capture, without the scene's shapes or points.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from cli_run import train  # noqa: E402
DATA = (ROOT / ".." / "shared" / "data").resolve()


def room_blender(out: Path, cache: Path) -> Path:
    """Write scenes/room.xml's views as a Blender-layout dataset in ``out`` (once; references cached in ``cache``)."""
    if (out / "transforms_test.json").is_file():
        return out
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from mi_gaussians.config import SceneConfig
    from mi_gaussians.data.camera import GL_TO_CV
    from mi_gaussians.data.scene_dataset import load_scene_dataset
    from mi_gaussians.imwrite import write_png

    ds = load_scene_dataset(ROOT / "scenes" / "room.xml", SceneConfig(init="random", init_points=1),
                            cache_root=cache, log=lambda s: print(s, file=sys.stderr))
    for split, views in (("train", ds.train), ("test", ds.test)):
        frames = []
        (out / split).mkdir(parents=True, exist_ok=True)
        for v in views:
            c = v.camera
            if abs(c.fx - c.fy) > 1e-6 * c.fx or abs(c.cx - c.width / 2) > 1e-6 or abs(c.cy - c.height / 2) > 1e-6:
                raise SystemExit(f"camera {c.name}: the Blender layout needs square pixels and a centred image")
            write_png(out / split / f"{v.name}.png", np.clip(v.load_image(), 0, 1))
            c2w = np.linalg.inv(c.world_to_camera) @ GL_TO_CV
            frames.append({"file_path": f"./{split}/{v.name}", "transform_matrix": c2w.tolist()})
        fov = 2 * math.atan(views[0].camera.width / (2 * views[0].camera.fx))
        (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}, indent=1))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["mi_objects_blender", "room_blender"])
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--out", default="/tmp/mi_gs_init")
    ap.add_argument("--cache", default="/tmp/mi_gs_depth/room/references",
                    help="scenes/room.xml's reference cache (default: benchmarks/depth.py's, shared)")
    args = ap.parse_args(argv)
    root = Path(args.out)
    rows = []
    for name in args.datasets:
        if name == "mi_objects_blender":
            src, extra = DATA / "mi_objects" / "blender", ["--white-background"]
        elif name == "room_blender":
            src, extra = room_blender(root / "room_blender" / "dataset", Path(args.cache)), []
        else:
            raise SystemExit(f"unknown dataset {name}")
        for init in ("cube", "frustum"):
            m = train(src, root / name / init, args.iterations, extra + ["--set", f"data.random_init={init}"])
            rows.append((name, init, m["mean"]["psnr"], m["mean"]["ssim"], m["gaussians"], m["training_seconds"] / 60))
    print(f"\n{args.iterations} iterations, 100k random initial points; held-out views\n")
    print("| dataset | data.random_init | PSNR | SSIM | Gaussians | minutes |")
    print("|---|---|---:|---:|---:|---:|")
    for name, init, psnr, ssim, n, minutes in rows:
        print(f"| {name} | {init} | {psnr:.2f} | {ssim:.4f} | {n:,} | {minutes:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
