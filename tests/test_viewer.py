"""The viewer (mi_gaussians.viewer, ``mi-gs view``, ``mi-gs optimize --view``): camera conversions to and from viser,
the frames of every render mode against the rasterizer, and -- in a real headless Chromium (Debian's, driven by
Playwright) -- the page shows the model as ``mi-gs render`` renders it from the same camera, a mouse drag changes
the picture, and training with a browser watching gives the same model as training without one."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mi_gaussians.data.camera import Camera
from mi_gaussians.model.gaussians import Gaussians
from test_cli import run
from mi_gaussians.viewer import (RENDER_MODES, StaticModel, TrainingView, Viewer, ViewerConfig, browser_url,
                                 camera_from_pose, image_size, pose_of_camera, render_image)

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "scenes" / "tiny_gaussians.ply"
CAMERA = ROOT / "scenes" / "tiny_gaussians_camera.json"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_camera_round_trip():
    rng = np.random.default_rng(0)
    rotations = [_random_rotation(rng) for _ in range(50)]
    rotations += [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    for R in rotations:
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, rng.normal(size=3)
        cam = Camera(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0, world_to_camera=w2c)
        wxyz, pos, fov = pose_of_camera(cam)
        back = camera_from_pose(wxyz, pos, fov, 640, 480)
        np.testing.assert_allclose(back.world_to_camera, w2c, atol=1e-12)
        assert back.fy == pytest.approx(500.0) and back.fx == pytest.approx(500.0)
    assert image_size(4 / 3, 1024) == (1024, 768) and image_size(0.5, 256) == (128, 256)
    assert image_size(float("nan"), 100) == (100, 100)


def test_the_printed_address_is_one_a_browser_opens():
    """A wildcard host becomes the loopback address (IPv4 or IPv6), an IPv6 address goes in brackets."""
    assert browser_url("0.0.0.0", 8080) == browser_url("", 8080) == "http://127.0.0.1:8080"
    assert browser_url("::", 8080) == "http://[::1]:8080"
    assert browser_url("fe80::1", 81) == "http://[fe80::1]:81"
    assert browser_url("127.0.0.1", 1) == "http://127.0.0.1:1" and browser_url("node7", 2) == "http://node7:2"


def test_frames_of_every_mode():
    import drjit as dr

    from mi_gaussians.raster.rasterize import render

    g = Gaussians.load(TINY)
    cam = Camera.from_json(CAMERA)
    rgb = render_image(g, cam, "RGB")
    with dr.suspend_grad():
        out = render(g, cam)
    expect = (np.clip(np.array(out.rgb), 0, 1) * 255 + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(rgb, expect)
    alpha = render_image(g, cam, "Alpha")
    np.testing.assert_array_equal(alpha[..., 0], (np.clip(np.array(out.alpha), 0, 1) * 255 + 0.5).astype(np.uint8))
    depth = render_image(g, cam, "Expected depth")
    hit = np.array(out.alpha) > 0.5
    assert depth[hit].max() > 0 and np.all(depth[~hit] == 0)
    heat = render_image(g, cam, "Gaussians per tile")
    assert heat.shape == (240, 320, 3) and heat.any() and not heat.all()
    # an empty model renders empty frames
    empty = Gaussians.from_numpy(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, 3)))
    for mode in RENDER_MODES:
        assert not render_image(empty, cam, mode).any(), mode
    with pytest.raises(ValueError, match="render mode"):
        render_image(g, cam, "X-ray")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _browser():
    if CHROMIUM is None:
        pytest.skip("no Chromium on this machine (Debian: apt-get install chromium) for the browser tests")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("Playwright is not installed (pip install '.[test]')")
    return sync_playwright, CHROMIUM


def _open(p, chromium, url, width, height):
    browser = p.chromium.launch(executable_path=chromium,
                                args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
    page = browser.new_page(viewport={"width": width, "height": height})
    page.goto(url)
    return browser, page


def _wait_for_rest(page, timeout=60.0, after: str | None = None) -> str:
    """Wait until the panel reports a full-size frame (and a different report than ``after``)."""
    t0 = time.time()
    while time.time() - t0 < timeout:
        text = page.inner_text("body")
        line = next((ln for ln in text.splitlines() if "(rest)" in ln), None)
        if line is not None and line != after:
            return line
        page.wait_for_timeout(200)
    raise AssertionError(f"the viewer sent no full-size frame within {timeout} s")


def _screenshot(page, path) -> np.ndarray:
    from PIL import Image

    page.screenshot(path=str(path))
    return np.asarray(Image.open(path).convert("RGB"), np.float64) / 255.0


def test_browser_shows_the_model_and_follows_the_mouse(tmp_path):
    """``mi-gs view`` in Chromium: the screenshot's picture is ``mi-gs render``'s from the same camera (outside the
    panel and the notification corner), and dragging the mouse changes it."""
    from PIL import Image

    sync_playwright, chromium = _browser()
    port = _free_port()
    import tempfile

    # (the installed mi-gs, run outside the source tree)
    proc = subprocess.Popen([str(Path(sys.executable).parent / "mi-gs"), "view", str(TINY), "--camera", str(CAMERA),
                             "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=tempfile.gettempdir())
    import threading

    watchdog = threading.Timer(240, proc.kill)         # (a hung viewer must not hang the suite)
    watchdog.start()
    try:
        url = None
        for line in proc.stdout:
            if line.startswith("mi-gs view:"):
                url = line.split(" at ")[1].split()[0]
                break
        assert url == f"http://127.0.0.1:{port}"
        W, H = 640, 480
        # the camera the viewer starts from, at the page's size (viser's cameras have a centred principal point)
        wxyz, pos, fov = pose_of_camera(Camera.from_json(CAMERA))
        cam = camera_from_pose(wxyz, pos, fov, W, H)
        cam.to_json(tmp_path / "cam.json")
        r = run("render", TINY, "--camera", tmp_path / "cam.json", "-o", tmp_path / "ref.png")
        assert r.returncode == 0, r.stderr
        ref = np.asarray(Image.open(tmp_path / "ref.png").convert("RGB"), np.float64) / 255.0
        with sync_playwright() as p:
            browser, page = _open(p, chromium, url, W, H)
            region = (slice(H // 3, H), slice(0, W // 2))          # below the notification, left of the panel
            b = ref[region]
            assert (b.max(axis=2) > 0.1).mean() > 0.2               # the model covers this region
            # The browser reports its camera a few times while the page lays out; on a loaded machine a report
            # can stay unchanged for the viewer's idle time (0.25 s), which then renders it at rest before the
            # start camera's report arrives. The picture must settle on the start camera's within 30 s.
            _wait_for_rest(page)
            t0 = time.time()
            while True:
                page.wait_for_timeout(500)
                a = _screenshot(page, tmp_path / "shot.png")[region]
                psnr = 10 * math.log10(1 / np.mean((a - b) ** 2))
                if psnr > 25:
                    break
                assert time.time() - t0 < 30, f"the picture is not the start camera's after 30 s: {psnr:.2f} dB"
            page.mouse.move(W * 0.4, H * 0.6)
            page.mouse.down()
            page.mouse.move(W * 0.6, H * 0.65, steps=12)
            page.mouse.up()
            # (the panel reports the frame after the drag: a moving one first, then one at rest. On a loaded machine
            # the drag's camera reports can reach the viewer after its idle time, which then draws only the frame at
            # rest: while no moving frame shows, the camera keeps moving, a few pixels to and fro)
            t0 = last = time.time()
            wiggle = 0
            while "(moving)" not in page.inner_text("body"):
                assert time.time() - t0 < 60, "no frame while the camera moved"
                if time.time() - last > 3:
                    page.mouse.move(W * 0.6, H * 0.65)
                    page.mouse.down()
                    for _ in range(10):
                        wiggle = 1 - wiggle
                        page.mouse.move(W * 0.6 + 4 * wiggle, H * 0.65, steps=2)
                        page.wait_for_timeout(50)
                    page.mouse.up()
                    last = time.time()
                page.wait_for_timeout(100)
            _wait_for_rest(page, after=None)
            page.wait_for_timeout(1000)
            moved = _screenshot(page, tmp_path / "moved.png")
            assert np.mean(np.abs(moved[region] - a)) > 0.02
            assert (moved[region].max(axis=2) > 0.1).mean() > 0.1
            browser.close()
    finally:
        watchdog.cancel()
        proc.terminate()
        proc.wait(timeout=30)


def test_training_with_a_browser_watching_trains_the_same_model(tmp_path):
    """``Trainer.run(monitor=...)`` with a viewer serving a connected Chromium: frames are rendered between
    iterations and the model at the end is the one a run without the viewer trains, bit for bit (one thread)."""
    import drjit as dr

    from mi_gaussians.optim.trainer import Trainer
    from synthetic_dataset import make_blender_dataset
    from test_train import load, small_config

    sync_playwright, chromium = _browser()
    scene = make_blender_dataset(tmp_path / "scene")
    cfg = dataclasses.replace(small_config(160), eval_every=80)
    before = dr.thread_count()
    dr.set_thread_count(1)
    try:
        plain = Trainer(load(scene, cfg), cfg, tmp_path / "plain", progress=False)
        plain.run()
        watched = Trainer(load(scene, cfg), cfg, tmp_path / "watched", progress=False)
        live = TrainingView(watched, refresh_seconds=0.0, curve_seconds=0.0, budget_seconds=1.0)
        viewer = Viewer(live, [], ViewerConfig(port=_free_port(), max_size=256, moving_size=64),
                        raster=cfg.raster, initial=load(scene, cfg).test[0].camera)
        live.viewer = viewer
        viewer.start()
        try:
            with sync_playwright() as p:
                browser, page = _open(p, chromium, viewer.url, 320, 240)
                t0 = time.time()
                while not viewer.has_clients() or viewer.poll() == 0:       # (the first frame: the client is there)
                    assert time.time() - t0 < 60, "no client connected"
                    time.sleep(0.05)
                frames = viewer.frames
                watched.run(monitor=live.training_monitor)
                assert viewer.frames > frames + 10                  # frames rendered while training
                assert live.seconds > 0
                browser.close()
        finally:
            viewer.stop()
    finally:
        dr.set_thread_count(before)
    for k, v in plain.gaussians.numpy().items():
        np.testing.assert_array_equal(watched.gaussians.numpy()[k], v, err_msg=k)
    assert json.loads((tmp_path / "watched" / "metrics.json").read_text())["mean"] == \
        json.loads((tmp_path / "plain" / "metrics.json").read_text())["mean"]


def test_view_misuse_gives_one_line(tmp_path):
    (tmp_path / "model.obj").write_text("x")
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    try:
        r = run("view", TINY, "--port", busy.getsockname()[1])
    finally:
        busy.close()
    assert r.returncode == 2 and "cannot serve there" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    for args, words in (((tmp_path / "missing.ply",), "not found"), ((tmp_path / "model.obj",), "expected a model"),
                        ((tmp_path,), "point_cloud.ply: missing")):
        r = run("view", *args)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
