"""``mi-gs view MODEL|RUN_DIR``: a model in the browser (viser), with the cameras and references of the run it
came from."""

from __future__ import annotations

from pathlib import Path

from .args import (add_background, add_model_input, add_viewer_options, background, check_viewer, existing,
                   is_model, model_suffixes, start_viewer, viewer_config)
from .errors import InputError, warn


def add_parser(sub) -> None:
    s = sub.add_parser("view", help="look at a model in the browser (viser): orbit, render modes, dataset cameras")
    add_model_input(s, "model.ply|.splat|.spz|.glb|.gltf, a point-cloud .ply (mi-gs points), or an mi-gs optimize "
                       "output folder",
                    antialiased="render with Mip-Splatting's 2D filter (default: as the run was trained)")
    s.add_argument("--camera", help="camera JSON to start from (default: the dataset's first camera)")
    add_background(s, "background colour (1 or 3 values; default: the run's)")
    add_viewer_options(s)


def viewable_model(path: Path):
    """The Gaussians of a model file; a point-cloud PLY (``mi-gs points``) as small opaque Gaussians, one per point
    (SH degree 0, the size of the nearest-neighbour spacing scaled by 0.5)."""
    from ..model.gaussians import Gaussians
    from ..model.point_ply import is_point_cloud, read_points

    if path.suffix.lower() == ".ply" and is_point_cloud(path):
        xyz, rgb = read_points(path)
        if not len(xyz):
            return Gaussians.load(path)                   # (empty: the caller says so)
        return Gaussians.from_points(xyz, rgb, sh_degree=0, initial_opacity=0.9, scale_factor=0.5)
    return Gaussians.load(path)


def run(args) -> int:
    from .. import run_folder
    from ..data.camera import Camera
    from ..runs import model_raster_config
    from ..viewer import StaticModel, Viewer
    from ..viewer_entries import default_camera, run_entries

    src = existing(args.input)
    check_viewer(args)                    # (the address and the frame size, before the model is loaded)
    model = src / run_folder.MODEL if src.is_dir() else src
    if src.is_dir() and not model.is_file():
        _check_not_training(src)
        raise InputError(f"{model}: missing (is {src} an mi-gs optimize output folder?)")
    if not is_model(model):
        raise InputError(f"{src}: expected a model ({', '.join(model_suffixes())}) or an mi-gs optimize output folder")
    raster = model_raster_config(model, args.antialiased, warn=warn)
    views, color_space, bg = [], "srgb", (0.0, 0.0, 0.0)
    if (model.parent / run_folder.CONFIG).is_file():
        try:
            record = run_folder.RunRecord.read(model.parent, "")
        except ValueError as e:
            warn(f"{e}; viewing the model alone")
        else:
            views, color_space, bg = run_entries(record, model.parent, warn)
    if args.background is not None:
        bg = background(args.background)
    g = viewable_model(model)
    if g.n == 0:
        raise InputError(f"{model}: the model has no Gaussians (nothing to look at)")
    initial = Camera.from_json(args.camera) if args.camera else None
    if initial is None and not views:
        initial = default_camera(g)
    viewer = Viewer(StaticModel(g), views, viewer_config(args), raster=raster, color_space=color_space,
                    background=bg, title=f"mi-gs view {src.name}", initial=initial)
    # (from the server's start on, every way out stops it within the bound: a Ctrl-C that lands between the line
    # below and the serving loop -- the moment a script that waits for the line sends it -- once left the server to
    # the interpreter's exit, which waited for its threads for more than a minute in CI)
    try:
        start_viewer(viewer, args)
        print(f"mi-gs view: {g.n:,} Gaussians at {viewer.url} (Ctrl-C stops)", flush=True)
        viewer.serve_forever()
    except KeyboardInterrupt:                     # (how a viewer is meant to end: not an error)
        pass
    finally:
        stop_within(viewer, STOP_SECONDS, warn)
    return 0


def _check_not_training(folder: Path) -> None:
    """A run folder whose run is still training has no model yet: said so (not "is it an output folder?")."""
    from .. import run_folder

    try:
        run_folder.RunLock(folder).check_free()
    except run_folder.FolderBusy:
        raise InputError(f"{folder}: a run is still training in this folder, and its model "
                         f"({run_folder.MODEL}) is written when it ends: view it then, or watch a run as it trains "
                         "with mi-gs optimize --view") from None


#: The longest wait for the viewer's server to stop after Ctrl-C (seconds)
STOP_SECONDS = 10.0


def stop_within(viewer, seconds: float, warn) -> None:
    """Stop the viewer's server, waiting for it at most ``seconds`` (every wait is bounded): a server thread that
    does not end must not keep the command alive. Past the bound, one line says so and the process exits at once.
    (The viewer that once outlived a test's SIGINT in CI by 60 s was not this: the suite had been started with
    SIGINT ignored, which its children inherit; ``tests/test_reliability_round2.py`` now gives the viewer a terminal's
    SIGINT.)"""
    import os
    import sys
    import threading

    t = threading.Thread(target=viewer.stop, name="mi-gs viewer stop", daemon=True)
    t.start()
    t.join(seconds)
    if t.is_alive():
        warn(f"the viewer's server did not stop within {seconds:g} s; exiting without waiting for it")
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
