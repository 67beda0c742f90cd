"""A real browser: our .glb shown by three.js' own Gaussian-splat renderer (three/addons ``GaussianSplat`` through
GLTFLoader and its KHR_gaussian_splatting plugin, WebGPURenderer on its WebGL2 backend) in Debian's Chromium, from
one of our cameras, its screenshot scored against our own render of that camera.

A round trip through our own reader cannot see a wrong frame, wrong SH signs or a wrong colour space (the writer and
the reader would agree with each other); this test can: the same model written with each of those mistakes scores
far lower. The model is scenes/tiny_gaussians.ply with strong random SH up to degree 3, so that the SH signs show.
The two renderers differ on purpose where the 3DGS implementations do (three.js cuts each splat at 2 sigma, we at 3;
it holds SH and colours in 8 bits), hence a floor in the low twenties and margins against the mistakes.
"""

from __future__ import annotations

import functools
import http.server
import math
import threading
import urllib.parse
from pathlib import Path

import numpy as np
import pytest

from mi_gaussians.model import frames, gltf
from mi_gaussians.model.ply import read_ply
from test_export_ecosystem import js_tools  # noqa: F401  (a fixture)

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "scenes" / "tiny_gaussians.ply"
CAMERA = ROOT / "scenes" / "tiny_gaussians_camera.json"
GLTF_FROM_PLY = np.diag([-1.0, -1.0, 1.0, 1.0])        # glTF's LUF from the PLY's RDF
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])              # OpenCV camera axes -> three.js' (y up, looking down -z)


def three_camera(cam, background=(0.0, 0.0, 0.0)) -> dict:
    """Our camera (OpenCV axes, the model's frame) as the page takes it: glTF's frame, three.js' camera axes."""
    c2w = GLTF_FROM_PLY @ np.linalg.inv(cam.world_to_camera) @ CV_TO_GL
    return {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "near": 0.01, "far": 100.0, "camera_to_world": c2w.tolist(), "background": list(background)}


def _serve(js: Path, data: Path):
    """An HTTP server on 127.0.0.1: tests/js at /, ``data`` at /data/."""

    class Handler(http.server.SimpleHTTPRequestHandler):
        def translate_path(self, path):
            path = urllib.parse.unquote(path.split("?", 1)[0])
            if path.startswith("/data/"):
                return str(data / Path(path[len("/data/"):]).name)
            return super().translate_path(path)

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(js)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def _browser():
    """(sync_playwright, Chromium's path), or a skip naming what is missing."""
    import shutil

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("no Chromium on this machine (Debian: apt-get install chromium) for the browser test")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("Playwright is not installed (pip install '.[test]')")
    return sync_playwright, chromium


def _psnr(a, b) -> float:
    return 10 * math.log10(1 / np.mean((np.asarray(a, np.float64) - b) ** 2))


def test_three_js_shows_our_glb_as_we_render_it(js_tools, tmp_path):  # noqa: F811
    import json

    from PIL import Image

    from mi_gaussians.data.camera import Camera
    from mi_gaussians.model.gaussians import Gaussians
    from mi_gaussians.raster.rasterize import render

    sync_playwright, chromium = _browser()
    p = read_ply(TINY)
    rng = np.random.default_rng(7)
    p["sh_rest"] = rng.uniform(-0.45, 0.45, (len(p["means"]), 15, 3)).astype(np.float32)
    flip = tuple(np.diag(GLTF_FROM_PLY)[:3])
    files = {"ours": gltf.glb_bytes(p),
             # the same model with one mistake each: SH signs not turned with the frame, no change of frame, sRGB
             # colours tagged as linear
             "sh_signs": gltf.glb_bytes({**p, "sh_rest": p["sh_rest"] * frames.sh_flip_signs(flip)[:, None]}),
             "frame": gltf.glb_bytes(frames.flip_axes(p, flip)),
             "colour_space": gltf.glb_bytes(p, "linear")}
    for name, data in files.items():
        (tmp_path / f"{name}.glb").write_bytes(data)
    cam = Camera.from_json(CAMERA)
    (tmp_path / "camera.json").write_text(json.dumps(three_camera(cam)))
    ref = np.clip(np.array(render(Gaussians.from_numpy(**p), cam, background=(0.0, 0.0, 0.0)).rgb, np.float64), 0, 1)
    server = _serve(js_tools, tmp_path)
    scores, titles = {}, {}
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            try:
                page = browser.new_page(viewport={"width": cam.width, "height": cam.height})
                for name in files:
                    page.goto(f"http://127.0.0.1:{server.server_address[1]}/browser/index.html"
                              f"?model=/data/{name}.glb&camera=/data/camera.json")
                    page.wait_for_function("document.title.startsWith('ready') || document.title.startsWith('error')",
                                           timeout=90_000)
                    titles[name] = page.title()
                    assert titles[name].startswith("ready"), titles[name]
                    page.screenshot(path=str(tmp_path / f"{name}.png"))
                    shot = np.asarray(Image.open(tmp_path / f"{name}.png").convert("RGB"), np.float64) / 255
                    scores[name] = _psnr(shot, ref)
            finally:
                browser.close()
    finally:
        server.shutdown()
    print(f"PSNR of three.js' pictures against ours ({titles['ours']}): "
          + ", ".join(f"{k} {v:.2f} dB" for k, v in scores.items()))
    assert scores["ours"] > 21.0, scores
    for mistake in ("sh_signs", "frame", "colour_space"):
        assert scores[mistake] < scores["ours"] - 3.0, (mistake, scores)
