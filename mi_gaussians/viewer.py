"""``mi-gs view``: a local web viewer of a model, on `viser <https://viser.studio>`_ (the library gsplat and nerfstudio
use). What the browser shows is rendered by our rasterizer on the active variant -- what the integrator renders --
and streamed as images; viser's client supplies the orbit / fly camera and the control panel.

    viewer = Viewer(StaticModel(g), views, ViewerConfig(port=8080), raster=cfg, color_space="srgb")
    viewer.start(); print(viewer.url)
    while True:
        viewer.poll()          # renders the frames clients wait for (the only thread that touches Dr.Jit)

Frames: while the camera moves, the longest image side is ``moving_size`` (interactive with a million Gaussians on
the CPU); ``idle_seconds`` after the last move the view is rendered again at ``max_size``. Render modes: RGB, alpha,
expected depth (turbo colour map between the 2nd and 98th percentiles of the visible depths) and the number of
Gaussians binned in each tile (log scale; tiles of 8x8 pixels on the CPU, 16x16 on CUDA): the rasterizer's work,
where it goes.

Panel: render mode, SH degree, background colour, frame sizes, and a camera list (the training and test cameras of
the model's dataset): choosing one moves the browser's camera there and shows that view's reference image in the
panel, beside the render. During training (``mi-gs optimize --view``) the trainer calls :meth:`Viewer.poll` between
iterations (rendering reads the parameters, never changes them) and :meth:`Viewer.show_history` for the loss and
test-PSNR curves.

Threads: viser answers the browser on its own threads; they only record what each client wants. Rendering happens in
:meth:`Viewer.poll`, on the caller's thread, so Dr.Jit is used from one thread only.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from .config import RasterConfig
from .data.camera import Camera, focal_from_fov, fov_from_focal
from .data.colmap import quaternion_to_matrix
from .viewer_entries import ViewEntry

RENDER_MODES = ("RGB", "Alpha", "Expected depth", "Gaussians per tile")


#: the sizes (longest image side, pixels) the viewer's panel offers: at rest, and while the camera moves
MAX_SIZE_RANGE = (128, 4096)
MOVING_SIZE_RANGE = (64, 2048)


@dataclass(frozen=True)
class ViewerConfig:
    host: str = "127.0.0.1"
    port: int = 8080
    max_size: int = 1024          # longest image side at rest (pixels)
    moving_size: int = 256        # longest image side while the camera moves
    idle_seconds: float = 0.25    # a view unchanged this long is rendered at max_size
    jpeg_quality: int = 90


class StaticModel:
    """A model that does not change: ``get()`` -> (Gaussians, version 0)."""

    def __init__(self, gaussians):
        self.gaussians = gaussians

    def get(self):
        return self.gaussians, 0


class TrainingView:
    """The model of a running :class:`~mi_gaussians.optim.trainer.Trainer` for a :class:`Viewer`, and the trainer's
    monitor (``Trainer.run(monitor=view.training_monitor)``): between iterations it serves the browser within a time
    budget, shows a new model at most every ``refresh_seconds`` and updates the curves every ``curve_seconds``.
    Set :attr:`viewer` before training."""

    def __init__(self, trainer, refresh_seconds: float = 1.0, curve_seconds: float = 2.0,
                 budget_seconds: float = 0.05):
        self.trainer, self.viewer = trainer, None
        self.refresh_seconds, self.curve_seconds, self.budget_seconds = refresh_seconds, curve_seconds, budget_seconds
        self._version, self._at, self._curves_at = 0, -math.inf, -math.inf
        self.seconds = 0.0        # time spent in the monitor (the viewer's cost to training)

    def close(self) -> None:
        """Stop the viewer (if it still runs)."""
        if self.viewer is not None:
            self.viewer.stop()
            self.viewer = None

    def get(self):
        now = time.perf_counter()
        if now - self._at >= self.refresh_seconds:
            self._version, self._at = self.trainer.step, now
        return self.trainer.gaussians, self._version

    def training_monitor(self, trainer) -> None:
        start = time.perf_counter()
        if self.viewer is not None and self.viewer.has_clients():
            try:
                self.viewer.poll(self.budget_seconds)
                if start - self._curves_at >= self.curve_seconds:
                    self._curves_at = start
                    self.viewer.show_history(trainer.history.to_dict())
            except Exception as e:          # the viewer must never cost the run: stop serving, train on
                import sys

                print(f"mi-gs: warning: the viewer failed ({type(e).__name__}: {e}); training goes on without it",
                      file=sys.stderr)
                self.close()
        self.seconds += time.perf_counter() - start


# ---------------------------------------------------------------------------------------------------- cameras
def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method: stable for every rotation)."""
    m = np.asarray(R, np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q) * (1 if q[0] >= 0 else -1)


def browser_url(host: str, port: int) -> str:
    """The address a browser on this machine opens for a server bound to ``host``: the loopback address of a
    wildcard (``0.0.0.0``, ``::``), an IPv6 address in brackets."""
    host = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
    return f"http://{f'[{host}]' if ':' in host else host}:{port}"


def image_size(aspect: float, longest: int) -> tuple[int, int]:
    """(width, height) of an image of ``aspect`` = width / height whose longest side is ``longest`` pixels."""
    aspect = float(aspect) if aspect and math.isfinite(aspect) and aspect > 0 else 1.0
    if aspect >= 1:
        return int(longest), max(1, int(round(longest / aspect)))
    return max(1, int(round(longest * aspect))), int(longest)


def camera_from_pose(wxyz, position, fov_y: float, width: int, height: int, name: str = "") -> Camera:
    """The pinhole camera of a viser camera: orientation ``wxyz`` (camera to world, OpenCV axes, as viser's),
    centre ``position``, vertical field of view ``fov_y`` (radians), square pixels, centred principal point."""
    R = quaternion_to_matrix(wxyz)
    w2c = np.eye(4)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ np.asarray(position, np.float64)
    f = focal_from_fov(height, fov_y)
    return Camera(width=width, height=height, fx=f, fy=f, cx=width / 2, cy=height / 2, world_to_camera=w2c,
                  name=name)


def pose_of_camera(cam: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz, position, vertical field of view) of ``cam`` for viser (the inverse of :func:`camera_from_pose`)."""
    R = cam.world_to_camera[:3, :3].T
    return _matrix_to_quat(R), -R @ cam.world_to_camera[:3, 3], fov_from_focal(cam.height, cam.fy)


# ---------------------------------------------------------------------------------------------------- images
def _turbo(x: np.ndarray) -> np.ndarray:
    from matplotlib import colormaps

    return colormaps["turbo"](np.clip(x, 0.0, 1.0))[..., :3]


def render_image(g, cam: Camera, mode: str = "RGB", sh_degree: int | None = None, background=(0.0, 0.0, 0.0),
                 raster: RasterConfig = RasterConfig(), color_space: str = "srgb",
                 exposure: np.ndarray | None = None) -> np.ndarray:
    """One frame of the viewer: (H, W, 3) uint8 of ``g`` seen by ``cam`` in render ``mode`` (see the module
    docstring). RGB is display-encoded: a model trained on linear radiance is sRGB-encoded here. ``exposure``: a
    training view's colour transform (3 x 4) or bilateral grid (L, H, W, 3, 4), applied to RGB as the training
    applied it (before the encoding)."""
    import drjit as dr

    from .imwrite import linear_to_srgb
    from .raster.rasterize import render

    if mode not in RENDER_MODES:
        raise ValueError(f"unknown render mode {mode!r} (expected one of {', '.join(RENDER_MODES)})")
    with dr.suspend_grad():
        if mode == "Gaussians per tile":
            return _tile_heat_map(g, cam, sh_degree, raster)
        out = render(g, cam, background=background, sh_degree=sh_degree, cfg=raster)
        if mode == "RGB":
            img = np.array(out.rgb, np.float32)
            if exposure is not None:
                from .metrics import apply_compensation

                img = apply_compensation(img, exposure)
            img = linear_to_srgb(np.maximum(img, 0)) if color_space == "linear" else img
        elif mode == "Alpha":
            img = np.repeat(np.array(out.alpha, np.float32)[..., None], 3, axis=2)
        else:
            depth, alpha = np.array(out.depth, np.float32), np.array(out.alpha, np.float32)
            hit = alpha > 0.5
            img = np.zeros(depth.shape + (3,), np.float32)
            if hit.any():
                lo, hi = np.percentile(depth[hit], [2, 98])
                img[hit] = _turbo((depth[hit] - lo) / max(hi - lo, 1e-12))
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _tile_heat_map(g, cam: Camera, sh_degree, raster: RasterConfig) -> np.ndarray:
    from .raster.binning import bin_gaussians
    from .raster.blend import lane_layout
    from .raster.projection import GaussianArrays, ViewParams, project

    W, H = cam.width, cam.height
    layout = lane_layout()
    cols, rows = layout.tile
    tx, ty = layout.tiles(W, H)
    counts = np.zeros(tx * ty)
    if g.n:
        view = ViewParams.from_camera(cam)
        proj = project(GaussianArrays.from_gaussians(g, g.sh_degree if sh_degree is None else sh_degree), view, raster,
                       layout.tile)
        bins = bin_gaussians(proj.depth, proj.rect, proj.tile_count, tx, ty, ellipse=proj.ellipse,
                             image_size=(view.width_f, view.height_f))
        counts = np.diff(np.array(bins.tile_start, np.int64)).astype(np.float64)
    tiles = np.log1p(counts.reshape(ty, tx)) / max(np.log1p(counts.max()), 1e-12)
    img = _turbo(np.repeat(np.repeat(tiles, rows, axis=0), cols, axis=1)[:H, :W])
    img[np.repeat(np.repeat(counts.reshape(ty, tx) == 0, rows, axis=0), cols, axis=1)[:H, :W]] = 0.0
    return (img * 255.0 + 0.5).astype(np.uint8)


# ---------------------------------------------------------------------------------------------------- viewer
@dataclass
class _ClientState:
    """What one browser wants (written by viser's threads, read by :meth:`Viewer.poll`)."""

    camera: tuple | None = None            # (wxyz, position, fov_y, aspect, canvas size) of the last camera message
    moved_at: float = 0.0                  # when the camera last changed
    drawn: tuple | None = None             # (camera, settings, model version, full size?) of the last frame sent
    frame_seconds: list = field(default_factory=list)


class Viewer:
    """The viewer server (see the module docstring). ``model``: an object with ``get()`` -> (Gaussians, version);
    ``views``: the dataset's cameras; ``background``: the initial background colour (linear 0..1 floats)."""

    def __init__(self, model, views: list[ViewEntry] | None = None, cfg: ViewerConfig = ViewerConfig(),
                 raster: RasterConfig = RasterConfig(), color_space: str = "srgb", background=(0.0, 0.0, 0.0),
                 title: str = "mi-gaussians", initial: Camera | None = None):
        self.model, self.views, self.cfg = model, list(views or []), cfg
        self.raster, self.color_space, self.title = raster, color_space, title
        self.initial = initial if initial is not None else (self.views[0].camera if self.views else None)
        self._background = tuple(float(b) for b in background)
        self._clients: dict[int, _ClientState] = {}
        self._lock = threading.Lock()
        self._jump: dict[int, ViewEntry] = {}
        self._chosen: ViewEntry | None = None      # the camera last chosen in the panel
        self.server = None
        self.frames = 0

    # ------------------------------------------------------------------ server
    def start(self) -> None:
        """Serve (OSError when ``host:port`` cannot be bound: viser itself would try the next ports, or wait
        forever for an address it cannot bind)."""
        import socket

        import viser

        try:
            infos = socket.getaddrinfo(self.cfg.host, self.cfg.port, type=socket.SOCK_STREAM)
        except socket.gaierror as e:
            raise OSError(f"unknown host {self.cfg.host!r} ({e})") from None
        family, _, _, _, address = infos[0]
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
        self.server = viser.ViserServer(host=self.cfg.host, port=self.cfg.port, label=self.title, verbose=False)
        self.server.gui.configure_theme(control_layout="floating", show_logo=False, dark_mode=True)
        if self.initial is not None:
            self._set_initial_camera(self.initial)
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(lambda client: self._forget(client.client_id))

    def _set_initial_camera(self, cam: Camera) -> None:
        """New clients start at ``cam``, orbiting the point on its axis as far away as the model's median centre."""
        wxyz, pos, fov = pose_of_camera(cam)
        R = quaternion_to_matrix(wxyz)
        g, _ = self.model.get()
        distance = 1.0
        if g.n:
            centre = np.median(np.array(g.means, np.float64).reshape(-1, 3), axis=0)
            distance = float(R[:, 2] @ (centre - pos)) if float(R[:, 2] @ (centre - pos)) > 1e-6 else 1.0
        up = -R[:, 1]
        self.server.scene.set_up_direction(tuple(float(u) for u in up))
        ic = self.server.initial_camera
        ic.position, ic.look_at, ic.up, ic.fov = pos, pos + distance * R[:, 2], up, fov

    @property
    def url(self) -> str:
        host = self.server.get_host() if self.server is not None else self.cfg.host
        return browser_url(host, self.server.get_port())

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    def has_clients(self) -> bool:
        with self._lock:
            return bool(self._clients)

    def _forget(self, client_id: int) -> None:
        with self._lock:
            self._clients.pop(client_id, None)

    def _build_gui(self) -> None:
        g, _ = self.model.get()
        gui = self.server.gui
        self._mode = gui.add_dropdown("Render mode", RENDER_MODES, initial_value="RGB")
        self._sh = gui.add_slider("SH degree", min=0, max=max(g.sh_degree, 1), step=1, initial_value=g.sh_degree,
                                  disabled=g.sh_degree == 0)
        self._bg = gui.add_rgb("Background", tuple(int(round(255 * min(max(b, 0.0), 1.0))) for b in self._background))
        self._max = gui.add_slider("Size at rest", min=MAX_SIZE_RANGE[0], max=MAX_SIZE_RANGE[1], step=32,
                                   initial_value=self.cfg.max_size)
        self._moving = gui.add_slider("Size moving", min=MOVING_SIZE_RANGE[0], max=MOVING_SIZE_RANGE[1], step=32,
                                      initial_value=self.cfg.moving_size)
        self._stats = gui.add_markdown("")
        names = ["(free)"] + [v.name for v in self.views]
        self._camera = gui.add_dropdown("Camera", names, initial_value="(free)", visible=bool(self.views))
        self._reference = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="Reference", visible=False)
        self._exposure = gui.add_checkbox("Exposure of the chosen view", initial_value=False,
                                          visible=any(v.exposure is not None for v in self.views),
                                          hint="render through the colour transform (--exposure) or bilateral "
                                               "grid (--exposure bilateral) fitted to this training view (the "
                                               "model itself has none)")
        self._curves = None

        @self._camera.on_update
        def _(event) -> None:
            entry = next((v for v in self.views if v.name == self._camera.value), None)
            with self._lock:
                self._chosen = entry
            if event.client is None:
                return
            if entry is not None:
                with self._lock:
                    self._jump[event.client.client_id] = entry

    def _on_connect(self, client) -> None:
        state = _ClientState()
        with self._lock:
            self._clients[client.client_id] = state

        @client.camera.on_update
        def _(camera) -> None:
            key = (tuple(np.round(camera.wxyz, 9)), tuple(np.round(camera.position, 9)), round(float(camera.fov), 9),
                   round(camera.aspect, 6), max(int(camera.image_width), int(camera.image_height)))
            with self._lock:
                if key != state.camera:
                    state.camera, state.moved_at = key, time.perf_counter()

    # ------------------------------------------------------------------ training
    def show_history(self, history: dict) -> None:
        """Loss and test-PSNR curves (``Trainer.history``) in the panel (created on first use)."""
        import viser.uplot as uplot

        it = np.asarray(history.get("iteration", []), np.float64)
        if self.server is None or len(it) < 2:
            return
        loss = np.asarray(history["loss"], np.float64)
        psnr = np.full(len(it), np.nan)
        evals = dict(zip(history.get("eval_iteration", []), history.get("test_psnr", [])))
        idx = {int(v): i for i, v in enumerate(it)}
        for step, value in evals.items():
            if int(step) in idx:
                psnr[idx[int(step)]] = value
        stride = max(1, len(it) // 2000)
        data = (it[::stride], loss[::stride])
        if self._curves is None:
            self._curves = self.server.gui.add_uplot(
                data=data, series=(uplot.Series(label="iteration"), uplot.Series(label="loss", stroke="orange")),
                title="training loss", aspect=1.6)
            self._psnr_text = self.server.gui.add_markdown("")
        else:
            self._curves.data = data
        if evals:
            last = max(evals)
            self._psnr_text.content = f"test PSNR {evals[last]:.2f} dB at iteration {int(last):,}"

    # ------------------------------------------------------------------ rendering
    def _settings(self) -> tuple:
        bg = tuple(c / 255.0 for c in self._bg.value)
        chosen = self._chosen
        exposure = (chosen.name if self._exposure.value and chosen is not None and chosen.exposure is not None
                    else None)
        return (self._mode.value, int(self._sh.value), bg, int(self._max.value), int(self._moving.value), exposure)

    def render_frame(self, gaussians, cam: Camera, settings: tuple | None = None) -> np.ndarray:
        """A frame (uint8) of ``gaussians`` from ``cam`` with the panel's settings (render mode, SH degree,
        background, the chosen training view's exposure)."""
        mode, sh, bg, _, _, exposure = settings or self._settings()
        matrix = None
        if exposure is not None:
            entry = next((v for v in self.views if v.name == exposure), None)
            matrix = None if entry is None or entry.exposure is None else np.asarray(entry.exposure(), np.float64)
        return render_image(gaussians, cam, mode, sh, bg, self.raster, self.color_space, exposure=matrix)

    def poll(self, budget_seconds: float | None = None) -> int:
        """Render and send the frames clients are waiting for (a moving camera at the small size, a camera at rest
        once more at the full size, a changed model or setting); returns how many frames were sent. ``budget``:
        stop starting frames after this many seconds."""
        if self.server is None:
            return 0
        t0 = time.perf_counter()
        sent = 0
        with self._lock:
            jumps, self._jump = self._jump, {}
            items = list(self._clients.items())
        for client_id, entry in jumps.items():
            self._jump_to(client_id, entry)
        gaussians, version = self.model.get()
        settings = self._settings()
        for client_id, state in items:
            if budget_seconds is not None and time.perf_counter() - t0 > budget_seconds:
                break
            with self._lock:
                camera, moved_at, drawn = state.camera, state.moved_at, state.drawn
            if camera is None:
                continue
            at_rest = time.perf_counter() - moved_at >= self.cfg.idle_seconds
            want = (camera, settings, version, at_rest)
            if drawn == want or (drawn is not None and drawn[:3] == want[:3] and drawn[3] and not at_rest):
                continue
            wxyz, pos, fov, aspect, canvas = camera
            # (at rest: no larger than the browser's canvas; moving: the small size)
            longest = min(settings[3], canvas) if at_rest and canvas > 0 else settings[3] if at_rest else settings[4]
            W, H = image_size(aspect, longest)
            start = time.perf_counter()
            img = self.render_frame(gaussians, camera_from_pose(wxyz, pos, fov, W, H), settings)
            client = self.server.get_clients().get(client_id)
            if client is None:
                continue
            client.scene.set_background_image(img, format="jpeg", jpeg_quality=self.cfg.jpeg_quality)
            seconds = time.perf_counter() - start
            with self._lock:
                state.drawn = want
                state.frame_seconds = (state.frame_seconds + [seconds])[-20:]
            self.frames += 1
            sent += 1
            self._stats.content = (f"{gaussians.n:,} Gaussians · {W}x{H} in {seconds * 1e3:.0f} ms "
                                   f"({'rest' if at_rest else 'moving'})")
        return sent

    def _jump_to(self, client_id: int, entry: ViewEntry) -> None:
        client = self.server.get_clients().get(client_id)
        if client is None:
            return
        wxyz, pos, fov = pose_of_camera(entry.camera)
        client.camera.position, client.camera.wxyz, client.camera.fov = pos, wxyz, fov
        if entry.reference is not None:
            ref = np.clip(np.asarray(entry.reference(), np.float32)[..., :3], 0, 1)
            self._reference.image = (ref * 255 + 0.5).astype(np.uint8)
            self._reference.label = f"Reference: {entry.name}"
            self._reference.visible = True

    def serve_forever(self, stop: threading.Event | None = None, interval: float = 0.01) -> None:
        """:meth:`poll` until ``stop`` is set (or forever)."""
        while stop is None or not stop.is_set():
            if not self.poll():
                time.sleep(interval)
