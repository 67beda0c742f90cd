"""Anti-aliasing benchmark: a model trained at full resolution, scored on its held-out views rendered at 1/4, 1/2,
1 and 2 times the training resolution, with and without ``--antialiased`` (both trained in this run, same seed).

    python benchmarks/antialiasing.py mi_objects_blender        # 7k iterations on ../shared/data/mi_objects/blender
    python benchmarks/antialiasing.py objects_xml               # 3k iterations on scenes/objects.xml

References at another scale:
  * mi_objects_blender: the dataset's own 200x200 images area-downsampled by the loader (``-r 2``, ``-r 4``); there
    is nothing to compare with at 2x (the dataset's generator is not here), so that column is left empty;
  * objects_xml: every test camera re-rendered by Mitsuba's path tracer at the scaled film size, at the scene's sample
    count, through the same target pipeline as the training references (sRGB-encoded, composited over the
    background).
Each model is trained with the command line (``mi-gs optimize``), as a user would; the scores use
``mi_gaussians.evaluate.evaluate_views`` with the mode the run was trained in.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = (ROOT / ".." / "shared" / "data").resolve()
SCALES = (0.25, 0.5, 1.0, 2.0)

# name -> (input, iterations, extra optimize options)
SETUPS = {
    "mi_objects_blender": (DATA / "mi_objects" / "blender", 7000, ["--white-background"]),
    "objects_xml": (ROOT / "scenes" / "objects.xml", 3000, []),
}


def train(name: str, out: Path, antialiased: bool, cache: Path) -> float:
    src, iterations, extra = SETUPS[name]
    cmd = [str(Path(sys.executable).parent / "mi-gs"), "optimize", str(src), "-o", str(out), "--iterations",
           str(iterations), "--eval-every", "0", "--quiet", *extra]
    if src.suffix == ".xml":
        cmd += ["--cache", str(cache)]
    if antialiased:
        cmd.append("--antialiased")
    if (out / "point_cloud.ply").is_file():
        print(f"{out}: trained already, reused", file=sys.stderr)
        return float(json.loads((out / "metrics.json").read_text())["training_seconds"])
    if (out / "checkpoints" / "ckpt.npz").is_file():
        cmd.append("--resume")
    t0 = time.time()
    subprocess.run(cmd, check=True)
    print(f"{out}: trained in {time.time() - t0:.0f} s", file=sys.stderr)
    return float(json.loads((out / "metrics.json").read_text())["training_seconds"])


def scaled_views(name: str, run: Path, scale: float, work: Path):
    """(views, background, colour space) of the run's held-out views at ``scale``, or None without references."""
    import numpy as np

    from mi_gaussians import run_folder
    from mi_gaussians.data.dataset import load_dataset

    record = run_folder.RunRecord.read(run, "")
    cfg = record.train
    d = cfg.data
    if name == "mi_objects_blender":
        if scale > 1:
            return None
        ds = load_dataset(record.dataset, resolution=round(1 / scale), background=d.background,
                          test_every=d.test_every, random_points=0)
        return ds.test, ds.background, ds.color_space

    from mi_gaussians.data.scene_dataset import composite_background, load_scene_dataset, reference_view
    from mi_gaussians.data.scene_file import load_scene
    from mi_gaussians.data.scene_references import reference_seed, render_reference
    from mi_gaussians.imwrite import write_exr

    scene_cfg = dataclasses.replace(cfg.scene, init="random", init_points=1)
    ds = load_scene_dataset(record.dataset, scene_cfg, cache_root=record.references_cache(run),
                            background=d.background, test_every=d.test_every, seed=d.seed, progress=False)
    if scale == 1:
        return ds.test, ds.background, ds.color_space
    scene = load_scene(Path(record.dataset), scene_cfg.defines)
    spp = int(json.loads((ds.references / "rig.json").read_text())["spp"])
    _, bg_linear = composite_background(d.background, scene_cfg.linear)
    views = []
    for i, v in enumerate(ds.test):
        cam = v.camera.scaled(round(v.camera.width * scale), round(v.camera.height * scale))
        path = work / f"x{scale:g}" / f"{cam.name}.exr"
        if not path.is_file():
            write_exr(path, render_reference(scene, cam, spp, reference_seed("test", i)))
        views.append(reference_view(cam, path, bg_linear, scene_cfg.linear))
    return views, np.asarray(d.background, np.float32), ds.color_space


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", choices=sorted(SETUPS))
    ap.add_argument("--out", default="/tmp/mi_gs_antialiasing")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args()
    import mitsuba as mi

    mi.set_variant(args.variant)
    from mi_gaussians import run_folder
    from mi_gaussians.evaluate import evaluate_views, summarize
    from mi_gaussians.model.gaussians import Gaussians

    root = Path(args.out) / args.dataset
    seconds = {aa: train(args.dataset, root / ("antialiased" if aa else "default"), aa, root / "references")
               for aa in (False, True)}
    rows = []
    for scale in SCALES:
        row = {"scale": scale}
        for aa in (False, True):
            run = root / ("antialiased" if aa else "default")
            got = scaled_views(args.dataset, run, scale, root / "scaled_references")
            if got is None:
                continue
            views, bg, color_space = got
            cfg = run_folder.RunRecord.read(run, "").train
            g = Gaussians.load_ply(run / run_folder.MODEL)
            scores, _ = evaluate_views(g, views, tuple(bg), cfg=cfg.raster, with_lpips=False,
                                       color_space=color_space)
            row["size"] = f"{views[0].camera.width}x{views[0].camera.height}"
            row["aa" if aa else "default"] = summarize(scores)
            row["gaussians_aa" if aa else "gaussians_default"] = g.n
        rows.append(row)

    print(f"\n{args.dataset}: test views at other scales, trained at scale 1 "
          f"(training: {seconds[False] / 60:.1f} min default, {seconds[True] / 60:.1f} min --antialiased)")
    print("| scale | image | PSNR default | PSNR --antialiased | difference | SSIM default | SSIM --antialiased |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        if "default" not in r:
            print(f"| {r['scale']:g}x | - | (no reference) | | | | |")
            continue
        a, b = r["default"], r["aa"]
        print(f"| {r['scale']:g}x | {r['size']} | {a['psnr']:.2f} | {b['psnr']:.2f} | {b['psnr'] - a['psnr']:+.2f} | "
              f"{a['ssim']:.4f} | {b['ssim']:.4f} |")
    g = rows[0]
    print(f"Gaussians: {g.get('gaussians_default')} default, {g.get('gaussians_aa')} --antialiased")
    (root / "table.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
