"""``mi-gs optimize SCENE -o OUTDIR``: fit Gaussians to a dataset folder (COLMAP, Blender, instant-ngp) or to the
path-traced references of a Mitsuba scene (.xml); ``--resume`` continues a run, ``--view`` watches it."""

from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path

from . import train_options
from .args import (add_output, add_viewer_options, check_viewer, existing, positive_int, start_viewer, viewer_config,
                   viewer_options_given)
from .errors import EXIT_DIVERGED, InputError, note


def add_parser(sub) -> None:
    s = sub.add_parser("optimize", help="fit Gaussians to a COLMAP / Blender / instant-ngp scene folder, or to "
                                        "path-traced references of a Mitsuba scene .xml")
    s.add_argument("scene", help="scene folder, or Mitsuba scene file (.xml)")
    add_output(s, "output folder", overwrite="start a new run in an output folder that holds one (cached references "
                                             "are kept)")
    groups = train_options.add_arguments(s)
    s.add_argument("--set", action="append", default=None, metavar="SECTION.FIELD=VALUE", dest="settings",
                   help="set any field of the training configuration (mi_gaussians/config.py), applied after the "
                        "other options, e.g. --set densify.min_opacity=0.1 --set optim.feature_lr=0.005; repeatable")
    s.add_argument("--resume", action="store_true", help="continue the run saved in the output folder")
    s.add_argument("--quiet", action="store_true", help="no progress bar and no information lines (warnings and "
                                                        "notes stay, and the final JSON)")
    s.add_argument("--view", action="store_true",
                   help="serve the viewer while training (mi-gs view's options below), with the loss curve")
    add_viewer_options(s)
    groups["scene"].add_argument("--cache", default=None,
                                 help="folder for the cached references (default OUTDIR/references)")
    groups["scene"].add_argument("--workers", type=positive_int, default=None,
                                 help="render the missing references on N Ray workers, each loading the scene once "
                                      "(the same files as one process renders; pip install 'mi-gaussians[ray]')")
    groups["scene"].add_argument("--address", default=None,
                                 help="with --workers: join this Ray cluster (default: start a local one)")


def run(args) -> int:
    from ..io_utils import check_output_folder
    from ..optim.trainer import TrainingDiverged
    from ..runs import Stopped, quiet, stopping_on_signals, to_stderr, train_run

    out = Path(args.output)
    src = existing(args.scene)
    check_output_folder(out)
    cfg, record = _config(args, src, out)
    _check_workers(args, src)
    if args.view:
        check_viewer(args)                # (the address and the frame size, before anything is loaded or trained)
    for flag in [] if args.view else viewer_options_given(args):
        note(f"{flag} has no effect in this run: it configures the viewer of --view, which this run does not serve")
    watch = (lambda trainer, ds: _training_view(args, trainer, ds, cfg)) if args.view else None
    try:
        with stopping_on_signals() as stop, _farm(args, src, cfg) as farm:
            result = train_run(src, out, cfg, record, overwrite=args.overwrite, cache=args.cache,
                               progress=not args.quiet, watch=watch, farm=farm, stop=stop,
                               log=quiet(to_stderr) if args.quiet else to_stderr)
    except TrainingDiverged as e:
        print(f"mi-gs: error: {e}", file=sys.stderr)
        return EXIT_DIVERGED
    except Stopped as e:
        print(f"mi-gs: {_stopped_line(e, args, src, out)}", file=sys.stderr, flush=True)
        return 128 + e.signum
    metrics = result.metrics
    summary = {"output": str(out), **metrics["mean"], "gaussians": metrics["gaussians"],
               "training_seconds": metrics["training_seconds"]}
    if "half_image" in metrics:     # (--exposure: the test views' right halves after a transform fitted on the left)
        summary["half_image"] = metrics["half_image"]["mean"]
        note("--exposure: compare half_image (the reference's protocol: a colour transform fitted on each test "
             "view's left half, the right half scored); psnr, ssim and lpips are of the views as rendered")
    if "poses" in metrics:          # (--pose-opt, data.pose_noise: the training cameras' errors, start and end)
        summary["pose_rotation_error_degrees"] = metrics["poses"]["rotation_error_degrees"]
        # (a fraction of the given training cameras' spread, not of metrics.json's "extent", the length scale)
        summary["pose_translation_error_of_camera_spread"] = metrics["poses"]["translation_error_of_extent"]
        if "reprojection_error_pixels" in metrics["poses"]:
            summary["pose_reprojection_error_pixels"] = {k: metrics["poses"]["reprojection_error_pixels"][k]
                                                         for k in ("start", "end")}
    print(json.dumps(summary, indent=2), flush=True)
    if result.watcher is not None and result.watcher.viewer is not None:
        _serve_until_stopped(result.watcher)
    return 0


def _stopped_line(e, args, src: Path, out: Path) -> str:
    import shlex
    import signal

    from ..run_folder import CHECKPOINT

    name = signal.Signals(e.signum).name
    if e.step is None:
        return (f"stopped by {name} before training began (nothing to resume; the same command starts again, reusing "
                "the references rendered so far)")
    again = ["mi-gs", "optimize", str(src), "-o", str(out), "--resume"] + (["--cache", args.cache] if args.cache
                                                                              else [])
    return (f"stopped by {name} at iteration {e.step}, saved in {out / CHECKPOINT}; continue with: "
            f"{shlex.join(again)}")


def _check_workers(args, src: Path) -> None:
    from ..data.scene_file import is_scene_file

    if args.address and not args.workers:
        raise InputError("--address joins a Ray cluster for --workers N (give both)")
    if args.workers and not is_scene_file(src):
        raise InputError(f"--workers renders the path-traced references of a scene .xml; {src} is a dataset folder")


@contextlib.contextmanager
def _farm(args, src: Path, cfg):
    """The Ray workers that render the references (``--workers``), connected for the run; None without."""
    if not args.workers:
        yield None
        return
    import mitsuba as mi

    from ..cluster.ray_cluster import connected
    from ..cluster.references import RayFarm

    with connected(args.address, num_cpus=None if args.address else args.workers):
        yield RayFarm(src, cfg.scene.defines, mi.variant(), workers=args.workers)


def _config(args, src: Path, out: Path):
    """(TrainConfig, the record of the run being resumed or None); nothing is written."""
    from .. import run_folder
    from ..data.scene_file import is_scene_file

    if args.resume and args.overwrite:
        raise InputError("give at most one of --resume and --overwrite")
    if args.resume and args.settings:
        raise InputError("--set cannot change a run being resumed (its settings are in OUTDIR/config.json)")
    run_folder.RunLock(out).check_free()            # (a folder in use is described as such, not by what it holds)
    if args.resume:
        record = run_folder.RunRecord.read(out, "nothing to resume (no config.json in the output folder)")
        return train_options.resumed_config(args, record.train, is_scene_file(src), str(out / run_folder.CONFIG)), \
            record
    cfg = train_options.new_run_config(args, is_scene_file(src))     # (a bad setting first, whatever the folder holds)
    run_folder.check_new_run(out, args.overwrite)
    return cfg, None


def _training_view(args, trainer, ds, cfg):
    """The viewer of a run being trained (``--view``): a :class:`~mi_gaussians.viewer.TrainingView` serving."""
    from ..viewer import TrainingView, Viewer
    from ..viewer_entries import dataset_entries

    live = TrainingView(trainer)
    names = [v.name for v in ds.train]
    exposure = None if trainer.exposure is None else (lambda: dict(zip(names, trainer.exposure.per_image())))
    live.viewer = Viewer(live, dataset_entries(ds, exposure), viewer_config(args), raster=cfg.raster,
                         color_space=ds.color_space, background=tuple(ds.background),
                         title=f"mi-gs optimize {Path(args.output).name}")
    start_viewer(live.viewer, args)
    print(f"mi-gs: training view at {live.viewer.url}", file=sys.stderr, flush=True)
    return live


def _serve_until_stopped(live) -> None:
    print(f"mi-gs: training done; the viewer stays at {live.viewer.url} (Ctrl-C stops)", file=sys.stderr, flush=True)
    try:
        live.viewer.serve_forever()
    except KeyboardInterrupt:                 # (the run is done: stopping the viewer is not an error)
        pass
    finally:
        live.close()
