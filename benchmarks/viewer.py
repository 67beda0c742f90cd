"""Viewer benchmark: frames per second of ``mi-gs view`` on the active variant, and what ``mi-gs optimize --view``
costs the training when a browser watches.

    python benchmarks/viewer.py                                   # 1M Gaussians; training on the tiny test scene
    python benchmarks/viewer.py --sizes 100000 1000000 --train-iterations 600 --variant cuda_ad_rgb

Frames: :func:`mi_gaussians.viewer.render_image` (render + readback + 8-bit encoding, what the viewer does per
frame) of ``benchmarks/render.py``'s scene (N Gaussians over a 1.2-radian frustum, degree-3 SH) at the viewer's
moving size (longest side 256) and rest sizes (1024, and 512), 4:3, the median of 5 frames after 2 warm-ups.

Training: the same run (the synthetic Blender scene of the tests, 200x200, ``--train-iterations`` iterations with
densification) trained without a viewer and with one that a headless Chromium (Debian's, through Playwright) is
connected to, each refresh rendering the model (once a second, as ``--view`` does); iterations per second of both
in this run (wall time of ``Trainer.run``, final evaluation included) and the ratio.
"""

from __future__ import annotations

import argparse
import shutil
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))


def frame_rates(sizes, variant: str) -> list[tuple]:
    import mitsuba as mi

    mi.set_variant(variant)
    import mi_gaussians as mig
    from mi_gaussians.viewer import camera_from_pose, image_size, render_image
    from render import make_scene

    rows = []
    for n in sizes:
        g = mig.Gaussians.from_numpy(**make_scene(n))
        for label, longest in (("moving", 256), ("rest", 512), ("rest", 1024)):
            W, H = image_size(4 / 3, longest)
            cam = camera_from_pose([1, 0, 0, 0], [0, 0, 0], 2 * np.arctan(0.6 * 3 / 4), W, H)
            render_image(g, cam)
            render_image(g, cam)
            ts = []
            for _ in range(5):
                t0 = time.perf_counter()
                render_image(g, cam)
                ts.append(time.perf_counter() - t0)
            t = statistics.median(ts)
            rows.append((n, label, f"{W}x{H}", t * 1e3, 1 / t))
    return rows


def training_cost(iterations: int) -> tuple[float, float, int]:
    """(iterations/s without a viewer, with a watching browser, frames rendered)."""
    import dataclasses

    from playwright.sync_api import sync_playwright

    from mi_gaussians.optim.trainer import Trainer
    from mi_gaussians.viewer import TrainingView, Viewer, ViewerConfig
    from synthetic_dataset import make_blender_dataset
    from test_train import load, small_config

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("no Chromium (apt-get install chromium) for the training-cost part")
    tmp = Path(tempfile.mkdtemp())
    scene = make_blender_dataset(tmp / "scene")
    cfg = dataclasses.replace(small_config(iterations), eval_every=0)
    plain = Trainer(load(scene, cfg), cfg, tmp / "plain", progress=False)
    w0 = time.perf_counter()
    plain.run()
    plain_wall = time.perf_counter() - w0
    watched = Trainer(load(scene, cfg), cfg, tmp / "watched", progress=False)
    live = TrainingView(watched)
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    viewer = Viewer(live, [], ViewerConfig(port=port), raster=cfg.raster,
                    initial=load(scene, cfg).test[0].camera)
    live.viewer = viewer
    viewer.start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox", "--use-angle=swiftshader",
                                                                          "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 800, "height": 600})
            page.goto(viewer.url)
            t0 = time.time()
            while not viewer.has_clients() or viewer.poll() == 0:
                if time.time() - t0 > 60:
                    raise SystemExit("the browser did not connect")
                time.sleep(0.05)
            frames = viewer.frames
            w0 = time.perf_counter()
            watched.run(monitor=live.training_monitor)
            wall = time.perf_counter() - w0
            browser.close()
    finally:
        viewer.stop()
    return plain.step / plain_wall, watched.step / wall, viewer.frames - frames


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1_000_000])
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--train-iterations", type=int, default=600, help="0: skip the training part")
    args = ap.parse_args(argv)
    rows = frame_rates(args.sizes, args.variant)
    print(f"\nViewer frames on {args.variant} (render + readback + encoding; median of 5)\n")
    print("| Gaussians | camera | image | ms per frame | frames/s |")
    print("|---:|---|---|---:|---:|")
    for n, label, size, ms, fps in rows:
        print(f"| {n:,} | {label} | {size} | {ms:.0f} | {fps:.1f} |")
    if args.train_iterations:
        plain, watched, frames = training_cost(args.train_iterations)
        print(f"\nTraining, {args.train_iterations} iterations: {plain:.1f} it/s without a viewer, {watched:.1f} it/s "
              f"with a browser watching ({frames} frames rendered): {watched / plain:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
