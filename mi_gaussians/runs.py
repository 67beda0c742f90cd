"""Runs: training one in its output folder, what a run trained on, and how to render its model. The library side of
``mi-gs optimize``, ``eval``, ``render``, ``view`` and ``sweep`` (and of the benchmarks).

    result = train_run(src, out, cfg)                    # one run in the folder out (locked while it trains)
    ds = training_dataset(src, cfg, out)                 # a dataset folder, or a scene file with its references
    record = RunRecord.read(out, "missing")              # (mi_gaussians.run_folder)
    ds = run_dataset(record, out)                        # what that run was trained on, to evaluate or view it
    raster = model_raster_config(out / "point_cloud.ply", antialiased=None)   # as the run rendered it
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .config import RasterConfig, TrainConfig
from .data.dataset import Dataset, load_dataset
from .data.scene_file import is_scene_file
from .run_folder import CAMERAS, CONFIG, GAUSSIAN_SCENE, MODEL, RunLock, RunRecord, references_root


def to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


#: How the lines a run says to its log begin when they are warnings (kept by ``--quiet``) rather than information
WARNINGS = ("note: ", "mi-gs: warning: ")


def quiet(log: Callable[[str], None]) -> Callable[[str], None]:
    """``log`` for the warnings only (``--quiet``): lines beginning with one of :data:`WARNINGS`."""
    return lambda line: log(line) if line.startswith(WARNINGS) else None


@dataclass
class RunResult:
    """What :func:`train_run` did: the metrics it wrote (``metrics.json``), its trainer, the iteration it resumed
    from (None for a new run) and the watcher it made (``watch``'s result)."""

    metrics: dict
    trainer: object
    resumed_from: int | None
    watcher: object = None


class Stopped(Exception):
    """A run stopped by a signal (:func:`stopping_on_signals`): ``step`` is the iteration of the checkpoint it wrote,
    None when it stopped before training began (nothing to resume: the references rendered so far are kept)."""

    def __init__(self, signum: int, step: int | None):
        self.signum, self.step = signum, step
        super().__init__(f"stopped by signal {signum}")


STOP_SIGNALS = ("SIGTERM", "SIGINT", "SIGHUP")


@contextlib.contextmanager
def on_stop_signals(handler):
    """``handler(signum, frame)`` on SIGTERM, SIGINT and SIGHUP (what Slurm, Kubernetes, Ray, Ctrl-C and a closed
    terminal send) while the block runs; the handlers before are restored. The main thread only."""
    import signal

    # pycolmap (its glog) puts a handler of its own on SIGTERM when it is first imported: one that prints a stack
    # trace and kills the process. Imported later (a COLMAP model, undistortion, triangulation), it would replace ours
    # underneath Python, and a SIGTERM during training would lose the iterations since the last checkpoint. (Ray's
    # core does the same when it starts: a driver of Ray enters this after connecting.) The signals are blocked
    # from before that import until ours are in place: glog's handler is not async-signal-safe (a SIGTERM that
    # reached it while the import was allocating deadlocked in malloc, and the process never ended); one that
    # arrives meanwhile waits, and reaches our handler as they are unblocked.
    signums = [getattr(signal, name) for name in STOP_SIGNALS if hasattr(signal, name)]
    masking = hasattr(signal, "pthread_sigmask")
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, signums) if masking else None
    before = {}
    try:
        import pycolmap  # noqa: F401

        for s in signums:
            before[s] = signal.signal(s, handler)
        if masking:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            masking = False
        yield
    finally:
        if masking:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for s, h in before.items():
            signal.signal(s, h)


@contextlib.contextmanager
def stopping_on_signals():
    """While a run goes on, SIGTERM, SIGINT and SIGHUP stop it cleanly: during training it finishes the iteration,
    writes a checkpoint and raises :class:`Stopped` with its iteration; before training it raises at once (every file
    is written atomically). A second signal ends the process at once (status 128 + the signal), which loses nothing
    either. Yields the object whose ``trainer`` attribute :func:`train_run` sets."""

    class State:
        trainer = None
        signum = None

    state = State()

    def handler(signum, frame):
        if state.signum is not None:
            os._exit(128 + signum)
        state.signum = signum
        if state.trainer is None:
            raise Stopped(signum, None)
        state.trainer.stop_signal = signum

    with on_stop_signals(handler):
        yield state


def train_run(src: str | Path, out: str | Path, cfg: TrainConfig, record: RunRecord | None = None,
              overwrite: bool = False, cache: str | None = None, progress: bool = True,
              watch: Callable | None = None, farm=None, log: Callable[[str], None] | None = to_stderr,
              stop=None) -> RunResult:
    """Train one run of ``cfg`` on ``src`` in the folder ``out``: a new one, or the run whose ``record`` is given
    (resumed from its checkpoint). The folder is locked for the run (one run per folder; a second process gets
    ``FolderBusy``). Everything is checked (references rendered, every image decoded, a resumed run's dataset
    unchanged) before an earlier run's outputs are touched; ``overwrite`` then removes them. ``watch(trainer, ds)``,
    when given, returns an object whose ``training_monitor`` the trainer calls between iterations and whose
    ``close()`` is called when the run fails (the viewer). ``farm``: renders a scene file's missing references
    elsewhere (see :mod:`mi_gaussians.cluster.references`). ``stop``: the state of :func:`stopping_on_signals`
    (a signal then stops the run with :class:`Stopped`). A diverged run raises ``TrainingDiverged``."""
    out = Path(out)
    check_outside_dataset(src, out)
    if cache is not None:
        check_outside_dataset(src, cache, "--cache")
    created = not out.exists()
    lock = RunLock(out)
    lock.acquire()                                # before anything is written into the folder
    try:
        from .run_folder import remove_temporary_files

        remove_temporary_files(out)
        return _train_locked(Path(src), out, cfg, record, overwrite, cache, progress, watch, farm, log, stop)
    except BaseException as e:
        if created:                               # (a run refused before it wrote anything leaves no folder)
            from .run_folder import Manifest

            Manifest(out).discard_if_unused()
            lock.release_and_remove_if_empty()
        if stop is not None and stop.signum is not None and not isinstance(e, Stopped):
            # (raised by the handler inside a Mitsuba or Dr.Jit call, which wrapped it in an error of its own)
            raise Stopped(stop.signum, None) from None
        raise
    finally:
        lock.release()


def check_outside_dataset(src: str | Path, out: str | Path, what: str = "-o") -> None:
    """``out`` does not lie in the dataset folder ``src`` (whose files a run reads): ValueError otherwise."""
    src, target = Path(src).resolve(), Path(out).resolve()
    if src.is_dir() and (target == src or src in target.parents):
        raise ValueError(f"{what} {out}: lies in the dataset folder {src}, which is read, never written: choose a "
                         "folder outside it")


def _train_locked(src: Path, out: Path, cfg: TrainConfig, record, overwrite, cache, progress, watch, farm,
                  log, stop) -> RunResult:
    from .data.dataset import check_trainable_size, fingerprint, verify_images
    from .data.pose_noise import perturbed_views
    from .optim.trainer import Trainer, TrainingStopped
    from .run_folder import POINTS, REFERENCES, Manifest, run_outputs

    manifest = Manifest(out)
    cache = cache or (record.references_cache(out) if record else None)
    if is_scene_file(src) and references_root(out, cache) == out / REFERENCES:
        manifest.check_free([REFERENCES])
        manifest.claim([REFERENCES])                  # (before the references are rendered into it)
    ds = training_dataset(src, cfg, out, cache=cache, progress=progress,
                          expect_key=record.references_key if record else None, farm=farm, log=log,
                          with_points=False)
    check_trainable_size(ds)
    if ds.layout != "mitsuba":          # (a scene file's are checked before its references are rendered)
        check_training_memory(ds, src)
    _warn_camera_problems(ds, log)
    digest = fingerprint(ds) if ds.layout != "mitsuba" else None    # (a scene file's references carry their own key)
    if record is not None:
        check_resumed_dataset(src, out, record, digest, log)
    given = [v.camera for v in ds.train]
    ds = perturbed_views(ds, cfg.data.pose_noise, cfg.data.seed)     # (data.pose_noise: known errors to measure)
    verify_images(ds.test, progress=progress)
    planned = run_outputs(cfg, [v.name for v in (ds.test or ds.train[:1])], ds.layout == "mitsuba")
    manifest.check_free(planned)                      # (a user's file where the run would write: refused)
    if not is_scene_file(src) and cache is None:
        manifest.check_free([POINTS])
    if record is None and not is_scene_file(src):     # (once all is checked; a resumed run's checkpoint holds its model)
        if cache is None and cfg.data.init in ("auto", "triangulate"):
            manifest.claim([POINTS])                  # (a triangulation's cache, kept by --overwrite)
        ds = initial_points(ds, cfg, points_root(out, cache), log)
    _check_scene_scale(ds, cfg, log)
    with decoding_progress(ds, progress) as ds:
        trainer = Trainer(ds, cfg, out, progress=progress, given_cameras=given)     # (decodes the training images)
    if record is None and log is not None:
        _note_if_never_refined(trainer, cfg, log)
        _say_empty_background(trainer, cfg, log)
    watcher = watch(trainer, ds) if watch is not None else None
    if stop is not None:
        stop.trainer = trainer                        # (from now on a signal lets the iteration finish)
        if stop.signum is not None:
            trainer.stop_signal = stop.signum
    try:
        if overwrite:
            manifest.remove_outputs()
        manifest.claim(planned)
        write_cameras(out / CAMERAS, ds)
        try:
            metrics = trainer.run(resume=record is not None, fingerprint=digest,
                                  monitor=None if watcher is None else watcher.training_monitor,
                                  run_id=None if record is None else record.run_id)
        except TrainingStopped as e:
            raise Stopped(e.signum, e.step) from None
        if log is not None and metrics.get("poses", {}).get("note"):
            log(f"note: {metrics['poses']['note']}")
        if ds.layout == "mitsuba":
            from .plugins.scene_xml import write_gaussian_scene

            cam = (ds.test or ds.train)[0].camera
            write_gaussian_scene(out / GAUSSIAN_SCENE, MODEL, cam, ds.color_space, ds.background,
                                 antialiased=cfg.raster.antialiased)
    except BaseException:
        if watcher is not None:
            watcher.close()
        raise
    return RunResult(metrics, trainer, trainer.resumed_from, watcher)


def check_training_memory(ds: Dataset, src) -> None:
    """The decoded training images and one training iteration fit in memory (:mod:`mi_gaussians.memory`; ValueError
    with the estimate otherwise), before anything is decoded."""
    from .memory import check_training

    check_training([(v.camera.width, v.camera.height) for v in ds.train], str(src),
                   advice="train on smaller images (a larger -r divisor: -r 2, 4 or 8) or on fewer of them")


def _warn_camera_problems(ds: Dataset, log: Callable[[str], None] | None) -> None:
    """One warning when training cameras have focal lengths far apart (:func:`~mi_gaussians.data.camera.
    intrinsics_problem`)."""
    from .data.camera import intrinsics_problem

    bad = [p for v in ds.train if (p := intrinsics_problem(v.camera)) is not None]
    if bad and log is not None:
        more = f" (and {len(bad) - 1} more training views)" if len(bad) > 1 else ""
        log(f"mi-gs: warning: {ds.root}: {bad[0]}{more}")


def _check_scene_scale(ds: Dataset, cfg: TrainConfig, log: Callable[[str], None] | None) -> None:
    """The run's length scale (``data.extent``): one note when it falls back to the cameras' spread, and the
    one-line error of :class:`~mi_gaussians.data.pointcloud.DegenerateScale` when it is 0 or not finite."""
    _, fallback = ds.scene_scale(cfg.data.extent)
    if fallback is not None and log is not None:
        log(f"note: {ds.root}: {fallback}")


class _CountingLoader:
    """An image loader that advances a progress bar the first time each of its images is decoded (the trainer decodes
    every training image as it starts); otherwise the loader it wraps."""

    def __init__(self, base, tick):
        self.base, self._tick = base, tick

    def load(self, path):
        out = self.base.load(path)
        self._tick(path)
        return out

    def __getattr__(self, name):
        if name in ("base", "_tick"):
            raise AttributeError(name)
        return getattr(self.base, name)


@contextlib.contextmanager
def decoding_progress(ds: Dataset, progress: bool = True):
    """``ds`` whose training views advance a progress bar on stderr ("loading training images", shown after
    ``PROGRESS_DELAY`` seconds) as they are first decoded, within the block (a large dataset takes minutes to decode;
    nothing else would show)."""
    if not progress or len(ds.train) < 2:
        yield ds
        return
    from tqdm import tqdm

    from .data.dataset import PROGRESS_DELAY

    bar = tqdm(total=len(ds.train), desc="loading training images", unit="image", leave=False, file=sys.stderr,
               delay=PROGRESS_DELAY)
    seen: set = set()

    def tick(path):
        if not bar.disable and path not in seen and len(seen) < len(ds.train):
            seen.add(path)
            bar.update(1)

    try:
        yield dataclasses.replace(ds, train=[dataclasses.replace(v, loader=_CountingLoader(v.loader, tick))
                                             for v in ds.train])
    finally:
        bar.close()
        bar.disable = True


def write_cameras(path: Path, ds: Dataset) -> None:
    """``cameras.json`` of a run: its training and test cameras, each an object in the camera JSON format that
    ``mi-gs render --camera`` and ``mi-gs view --camera`` take (README, "Camera JSON"), named like the views."""
    import json

    from .io_utils import atomic_write_text

    atomic_write_text(path, json.dumps({"train": [v.camera.to_dict() for v in ds.train],
                                        "test": [v.camera.to_dict() for v in ds.test]}, indent=1) + "\n")


def _note_if_never_refined(trainer, cfg: TrainConfig, log: Callable[[str], None]) -> None:
    """One line when no refinement of the strategy falls within the run (e.g. a run shorter than its start): the run
    adds no Gaussians."""
    n = cfg.optim.iterations
    if not any(trainer.strategy.refines_at(s) for s in range(1, n)):
        fields = (("mcmc", ("refine_start_iter", "refine_stop_iter", "refine_every")) if cfg.strategy == "mcmc" else
                  ("densify", ("densify_from_iter", "densify_until_iter", "densification_interval")))
        section = getattr(cfg, fields[0])
        said = ", ".join(f"{fields[0]}.{f} = {getattr(section, f):,}" for f in fields[1])
        log(f"note: no densification falls within the {n:,} iterations ({said}): the run trains the initial "
            f"{trainer.params.n:,} Gaussians and adds none")


def _say_empty_background(trainer, cfg: TrainConfig, log: Callable[[str], None]) -> None:
    """One line when the run fits an object on an empty background with the default strategy: the rules for the
    floaters of the empty space (optim/densify.py) that fall within its iterations."""
    strategy, d, n = trainer.strategy, cfg.densify, cfg.optim.iterations
    if not getattr(strategy, "empty_background", False):
        return
    why = ("the training images have transparent pixels" if d.empty_background == "auto"
           else "densify.empty_background=on")
    reset = (f"an opacity reset at iteration {d.densify_from_iter:,}" if strategy.resets_at(d.densify_from_iter)
             and d.densify_from_iter < n else "no opacity reset at densify.densify_from_iter within the run")
    prunes = [s for s in range(1, n) if strategy.screen_prunes_at(s)]
    prune = (f"the screen-size prune at {strategy.screen_fraction:g} of the image at iterations {prunes[0]:,}-"
             f"{prunes[-1]:,}" if prunes else "no screen-size prune within the run")
    log(f"an object on an empty background ({why}): {reset} and {prune} (densify.empty_background=off: the "
        "reference's rules)")


def check_resumed_dataset(src: Path, out: Path, record: RunRecord, fingerprint: str | None,
                          log: Callable[[str], None] | None = to_stderr) -> None:
    """A resumed run trains on the folder it started on, with the same content (ValueError otherwise)."""
    if Path(record.dataset) != Path(src).resolve():
        raise ValueError(f"--resume: the run in {out} was trained on {record.dataset}, not on {Path(src).resolve()} "
                         f"(recorded in {out / CONFIG})")
    recorded = record.dataset_fingerprint
    if fingerprint is not None and recorded is not None and recorded.split(":")[0] != fingerprint.split(":")[0]:
        if log is not None:
            log(f"mi-gs: warning: {out / CONFIG} holds a dataset fingerprint of an earlier mi-gs; the dataset's "
                "content is not compared this time (the run's record gets the current one)")
    elif fingerprint is not None and recorded is not None and recorded != fingerprint:
        raise ValueError(f"--resume: {src}: the dataset changed since the run in {out} started (its images, "
                         "cameras or points differ); start a new run (--overwrite or another folder)")


def training_dataset(src: str | Path, cfg: TrainConfig, out: str | Path, cache: str | None = None,
                     progress: bool = True, expect_key: str | None = None, render_missing: bool = True,
                     farm=None, log: Callable[[str], None] | None = to_stderr, with_points: bool = True) -> Dataset:
    """The dataset a run of ``cfg`` in ``out`` trains on, with the points it starts from: a dataset folder (COLMAP,
    Blender, instant-ngp; :func:`initial_points`), or a Mitsuba scene file whose path-traced references are cached in
    ``cache`` (default OUTDIR/references); references missing from the cache are rendered (by ``farm`` when given)
    unless ``render_missing`` is False. ``expect_key``: the references key of the run being resumed (a scene that
    changed since is refused before anything is rendered). ``with_points=False``: a dataset folder's points as the layout
    gives them (nothing triangulated; :func:`initial_points` does the rest)."""
    d = cfg.data
    if is_scene_file(src):
        from .data.scene_dataset import load_scene_dataset

        return load_scene_dataset(src, cfg.scene, cache_root=references_root(Path(out), cache), background=d.background,
                                  test_every=d.test_every, seed=d.seed, progress=progress, log=log,
                                  expect_key=expect_key, render_missing=render_missing, farm=farm,
                                  triangulation=cfg.triangulate)
    ds = load_dataset(src, resolution=d.resolution, background=d.background, test_every=d.test_every,
                      random_points=d.random_points, seed=d.seed, masks=d.masks,
                      random_init="frustum" if d.init == "frustum" else "cube",
                      own_points=d.init in ("auto", "points"))
    return initial_points(ds, cfg, points_root(Path(out), cache), log) if with_points else ds


def points_root(out: Path, cache: str | None) -> Path:
    """Where a run's triangulated points are cached: ``cache``/points when given, else OUTDIR/points."""
    return (Path(cache) if cache else Path(out)) / "points"


def initial_points(ds: Dataset, cfg: TrainConfig, cache: Path, log: Callable[[str], None] | None = to_stderr) -> Dataset:
    """``ds`` with the points a run of ``cfg`` starts from (``data.init``, :data:`mi_gaussians.config.INITS`): the
    layout's own, triangulated from the posed training images (cached in ``cache``), or random; 'auto' takes the
    first of these that there is (triangulated points joined by the random ones when the images have alpha:
    :func:`_has_alpha`), and says which (and why) in one line to ``log``."""
    say = log or (lambda line: None)
    init, n_random = cfg.data.init, cfg.data.random_points
    own = ds.points_from == "layout"
    if init == "points" and not own:
        raise ValueError(f"{ds.root}: the {ds.layout} layout has no points of its own (data.init=points); use "
                         "--init triangulate, or auto")
    if init in ("points", "auto") and own:
        say(f"initial points: the dataset's own {len(ds.points_xyz):,}")
        return ds
    if init in ("cube", "frustum"):
        say(f"initial points: {n_random:,} random ({init})")
        return ds
    from .data.dataset import fingerprint
    from .data.triangulate import NoPoints, cache_key, triangulate

    work = cache / cache_key(fingerprint(ds), cfg.triangulate, cfg.data.seed)
    try:
        tri = triangulate(ds.train, ds.color_space, work, cfg.triangulate, cfg.data.seed, where=str(ds.root), log=log)
        if len(tri.xyz) < cfg.triangulate.min_points:
            raise NoPoints(f"{ds.root}: triangulation kept {len(tri.xyz):,} points, fewer than "
                             f"triangulate.min_points ({cfg.triangulate.min_points})")
    except NoPoints as e:
        if init == "triangulate":
            raise
        say(f"initial points: {n_random:,} random in the cube, since no points could be triangulated ({e})")
        return ds
    line = f"initial points: {len(tri.xyz):,} triangulated from the {len(ds.train)} posed training images"
    if init == "auto" and ds.points_xyz is not None and len(ds.points_xyz) and _has_alpha(ds):
        say(f"{line} + the {len(ds.points_xyz):,} random ({ds.points_from}), since the images have alpha (an "
            "object on an empty background)")
        return dataclasses.replace(ds, points_xyz=np.concatenate([tri.xyz, ds.points_xyz]).astype(np.float32),
                                   points_rgb=np.concatenate([tri.rgb, ds.points_rgb]).astype(np.float32),
                                   points_from=f"triangulated+{ds.points_from}")
    say(line)
    return dataclasses.replace(ds, points_xyz=tri.xyz, points_rgb=tri.rgb, points_from="triangulated")


def _has_alpha(ds: Dataset) -> bool:
    """Whether the training images carry alpha (an RGBA file or a mask; the first image speaks for all): 'auto' then
    adds the random points to the triangulated ones. Measured (benchmarks/init.py, README): an object on an empty
    background trains better from both (the random points fill what was not triangulated: mi_objects/blender 3k,
    31.95 dB against 31.28 triangulated alone and 31.84 the cube alone), while in a scene that fills the views
    random points float in front of the cameras (room_blender 3k: 8.31 dB with them, 31.11 without)."""
    return bool(ds.train) and ds.train[0].loader.load(ds.train[0].image_path)[1] is not None


def run_dataset(record: RunRecord, out: str | Path, dataset: str | None = None, render_missing: bool = True,
                progress: bool = True, log: Callable[[str], None] | None = to_stderr) -> Dataset:
    """The views a run is evaluated or viewed on: those of ``dataset``, else of the dataset it was trained on (a
    scene file's references from the run's cache, rendered again only if they are gone and ``render_missing``),
    with the run's resolution, background and split; no initial points. The run's own dataset's training views have
    the cameras the run trained from (``data.pose_noise``) or refined (``--pose-opt``: :func:`refined_training_cameras`);
    test views always keep the dataset's."""
    cfg, out = record.train, Path(out)
    src = Path(dataset or record.dataset)
    d = cfg.data
    if is_scene_file(src):
        cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, init="random", init_points=1))
        ds = training_dataset(src, cfg, out, cache=record.references_cache(out), progress=progress,
                              expect_key=record.references_key, render_missing=render_missing)
    else:
        ds = load_dataset(src, resolution=d.resolution, background=d.background, test_every=d.test_every,
                          random_points=0, masks=d.masks)
    if dataset is not None and src.resolve() != Path(record.dataset).resolve():
        return ds
    from .data.pose_noise import perturbed_views

    return refined_training_cameras(perturbed_views(ds, d.pose_noise, d.seed), out, log)


def refined_training_cameras(ds: Dataset, out: str | Path, log: Callable[[str], None] | None = to_stderr) -> Dataset:
    """``ds`` (the dataset of the run in ``out``) with the training cameras the run refined (``--pose-opt``:
    ``cameras_refined.json``), matched by name; ``ds`` as it is where the run has none, or (said in one line to
    ``log``) where the file is damaged or holds other views."""
    from .run_folder import REFINED_CAMERAS

    path = Path(out) / REFINED_CAMERAS
    if not path.is_file():
        _warn_if_refined_missing(out, path, log)
        return ds
    try:
        refined = _refined_cameras(path)
        if sorted(refined) != sorted(v.name for v in ds.train):
            raise ValueError(f"{path}: its cameras are not the training views of the run's dataset")
    except ValueError as e:
        if log is not None:
            log(f"mi-gs: warning: {e}; the training views keep the dataset's cameras")
        return ds
    return dataclasses.replace(ds, train=[_moved(v, refined[v.name]) for v in ds.train])


def _moved(view, refined):
    """``view`` seen from the pose of ``refined`` (a refined camera of the same view), with its own intrinsics: a
    refinement moves the camera, and a dataset loaded at another resolution (``-r``) keeps its image size."""
    return dataclasses.replace(view, camera=dataclasses.replace(view.camera,
                                                                world_to_camera=refined.world_to_camera.copy()))


def _warn_if_refined_missing(out: str | Path, path: Path, log: Callable[[str], None] | None) -> None:
    """One warning when the run in ``out`` refined its cameras (``--pose-opt``) and ``path`` (its
    ``cameras_refined.json``) is gone: its training views are then seen from the unrefined cameras."""
    try:
        refined_run = RunRecord.read(Path(out), "").train.optim.pose_opt
    except ValueError:
        return
    if refined_run and log is not None:
        log(f"mi-gs: warning: {path}: missing, though the run refined its training cameras (--pose-opt); the "
            "training views keep the dataset's cameras, which the model was not trained from")


def _refined_cameras(path: Path) -> dict:
    """The cameras of a run's ``cameras_refined.json`` by name (ValueError naming the file when it is damaged)."""
    from .data.camera import Camera
    from .io_utils import read_json_object

    entries = read_json_object(path, "refined cameras", '{"train": [camera, ...]}').get("train")
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ValueError(f"{path}: expected \"train\": a list of cameras")
    return {c.name: c for c in (Camera.from_dict(e, source=str(path)) for e in entries)}


def model_raster_config(model: str | Path, antialiased: bool | None = None,
                        warn: Callable[[str], None] | None = None) -> RasterConfig:
    """How to render the model file ``model``: as the run whose ``config.json`` sits beside it was trained (a PLY
    records nothing about anti-aliasing), or as an ``.spz`` file records it, unless ``antialiased`` says otherwise;
    the defaults for a lone model. A ``config.json`` that is not a valid run record is passed to ``warn`` (a line)
    and the defaults are used."""
    model = Path(model)
    cfg = RasterConfig()
    if model.suffix.lower() == ".spz" and antialiased is None:      # (an .spz file records it)
        from .model.web_formats import read_model

        return dataclasses.replace(cfg, antialiased=bool(read_model(model)[1]))
    if (model.parent / CONFIG).is_file():
        try:
            cfg = RunRecord.read(model.parent, "").train.raster
        except ValueError as e:      # e.g. another tool's config.json: not a run record
            if antialiased is None and warn is not None:
                warn(f"rendering with the default settings: {e}")
    return cfg if antialiased is None else dataclasses.replace(cfg, antialiased=antialiased)


def model_run_cameras(model: str | Path, ds: Dataset, log: Callable[[str], None] | None = to_stderr) -> Dataset:
    """``ds`` with the refined training cameras of the run whose folder holds the model file ``model``, when that run
    refined them (``--pose-opt``) and ``ds`` is the dataset it trained on, at any resolution (the refined poses with
    ``ds``'s intrinsics; said in one line to ``log``, as a refined run whose file is missing is); else ``ds``."""
    from .run_folder import REFINED_CAMERAS

    folder = Path(model).parent
    if not (folder / CONFIG).is_file():
        return ds
    try:
        record = RunRecord.read(folder, "")
    except ValueError:
        return ds
    if Path(record.dataset).resolve() != Path(ds.root).resolve():
        return ds
    path = folder / REFINED_CAMERAS
    if not path.is_file():
        _warn_if_refined_missing(folder, path, log)
        return ds
    try:            # (by name, in either split: the run may have split the views otherwise, e.g. --test-every 0)
        refined = _refined_cameras(path)
        if not set(refined) <= {v.name for v in ds.views}:
            raise ValueError(f"{path}: its cameras are not views of {ds.root}")
    except ValueError as e:
        if log is not None:
            log(f"mi-gs: warning: {e}; the training views keep the dataset's cameras")
        return ds
    if log is not None:
        log(f"note: the run's training views use the cameras it refined ({path})")

    def moved(views):
        return [_moved(v, refined[v.name]) if v.name in refined else v for v in views]

    return dataclasses.replace(ds, train=moved(ds.train), test=moved(ds.test))
