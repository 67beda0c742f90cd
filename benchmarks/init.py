"""Initial points of posed datasets without points of their own, in the same run with the same seed: ``--init auto``
(the default: here, points triangulated from the posed training images, joined by the cube's when the images have
alpha), the reference's random cube and the frustum sampler, at 3k and 7k iterations. Prints PSNR / SSIM on the held-out views, the final count, the initial point count
and the seconds each stage of the triangulation took.

    python benchmarks/init.py                                   # every dataset below, 3k and 7k
    python benchmarks/init.py --datasets room_blender --iterations 3000

Datasets:
  * room_blender: scenes/room.xml's 32 declared cameras inside a 4 x 2.6 x 4 room, path-traced by Mitsuba (the rig and
    reference code of ``mi-gs optimize scenes/room.xml``) and written in the Blender layout (sRGB PNGs,
    transforms_train.json / transforms_test.json with every 8th camera held out), so that it trains like any Blender
    capture, without the scene's shapes or points;
  * mi_room_blender: ../shared/data/mi_room/blender (35 training views, 256x256, a room seen from inside);
  * mi_objects_blender: ../shared/data/mi_objects/blender (white background);
  * fox: ../shared/data/fox (instant-ngp layout, a phone capture) at -r 8.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from cli_run import train  # noqa: E402
DATA = (ROOT / ".." / "shared" / "data").resolve()
INITS = ("auto", "cube", "frustum")


def room_blender(out: Path, cache: Path) -> Path:
    """Write scenes/room.xml's views as a Blender-layout dataset in ``out`` (once; references cached in ``cache``)."""
    from scene_blender import write_dataset

    return write_dataset(ROOT / "scenes" / "room.xml", out, cache, alpha=False)


def dataset(name: str, root: Path, cache: Path) -> tuple[Path, list[str]]:
    if name == "room_blender":
        return room_blender(root / "room_blender" / "dataset", cache), []
    if name == "mi_room_blender":
        return DATA / "mi_room" / "blender", []
    if name == "mi_objects_blender":
        return DATA / "mi_objects" / "blender", ["--white-background"]
    if name == "fox":
        return DATA / "fox", ["-r", "8"]
    raise SystemExit(f"unknown dataset {name}")


def triangulation(run: Path) -> tuple[int | None, dict]:
    """(point count, seconds per stage) of a run's triangulation (its cached result), (None, {}) without."""
    found = sorted((run / "points").glob("*/points.npz"))
    if not found:
        return None, {}
    with np.load(found[0]) as z:
        return int(len(z["xyz"])), json.loads(str(z["seconds"]))


def initial_count(run: Path) -> int:
    """The Gaussians a run started from (its first logged iteration: nothing is densified or pruned before 500)."""
    history = json.loads((run / "history.json").read_text())
    assert history["iteration"][0] < 500, history["iteration"][0]
    return int(history["gaussians"][0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["room_blender", "mi_room_blender", "mi_objects_blender", "fox"])
    ap.add_argument("--iterations", nargs="+", type=int, default=[3000, 7000])
    ap.add_argument("--inits", nargs="+", choices=INITS, default=list(INITS),
                    help="which initial point sources to train (default: all, in this order)")
    ap.add_argument("--out", default="/tmp/mi_gs_init")
    ap.add_argument("--cache", default="/tmp/mi_gs_depth/room/references",
                    help="scenes/room.xml's reference cache (default: benchmarks/depth.py's, shared)")
    args = ap.parse_args(argv)
    root = Path(args.out)
    rows = []
    for iterations in args.iterations:                 # (the shorter runs of every dataset first)
        for name in args.datasets:
            src, extra = dataset(name, root, Path(args.cache))
            if not src.is_dir():
                print(f"{name}: {src} not found, skipped", file=sys.stderr)
                continue
            for init in [i for i in INITS if i in args.inits]:
                run = root / name / f"{init}_{iterations}"
                m = train(src, run, iterations, extra + ["--init", init])
                triangulated, seconds = triangulation(run)
                count = initial_count(run)
                rows.append((name, iterations, init, count, triangulated, seconds, m))
                print(f"{name} {iterations} {init}: {m['mean']['psnr']:.2f} dB, {m['gaussians']:,} Gaussians, "
                      f"initial points {count:,} ({triangulated or 0:,} triangulated)", file=sys.stderr, flush=True)
    print("\nPSNR / SSIM on the held-out views; one run each, 2-core machine\n")
    print("| dataset | iterations | --init | initial points | triangulation s (images, features, matching, "
          "triangulation) | PSNR | SSIM | Gaussians | minutes |")
    print("|---|---:|---|---:|---|---:|---:|---:|---:|")
    for name, iterations, init, count, triangulated, seconds, m in rows:
        stages = " + ".join(f"{seconds[k]:.1f}" for k in ("images", "features", "matching", "triangulation")
                            if k in seconds) or ""
        random = count - (triangulated or 0)
        points = " + ".join(([f"{triangulated:,} triangulated"] if triangulated else [])
                            + ([f"{random:,} random"] if random else []))
        print(f"| {name} | {iterations:,} | {init} | {points} | {stages} | {m['mean']['psnr']:.2f} | "
              f"{m['mean']['ssim']:.4f} | {m['gaussians']:,} | {m['training_seconds'] / 60:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
