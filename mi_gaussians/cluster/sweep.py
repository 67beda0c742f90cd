"""``mi-gs sweep``: every run of a spec (:mod:`.sweep_spec`) as a Ray task writing an ordinary run folder,
``OUT/runs/<name>/`` (readable by ``mi-gs eval`` and ``view``), and the table of their results (:mod:`.results`).

No work is lost: runs checkpoint; a task whose worker dies (a killed process, a lost node) is run again by Ray
(``retries``) and resumes from its checkpoint; a sweep run again on the same OUT skips the finished runs and resumes
the others; a run that fails for a reason of its own (a bad dataset, a diverged loss) is recorded as failed with its
one-line message, and the others go on. The scene files' references are rendered first, by Ray workers, and the
datasets' initial points triangulated (once each) into ``OUT/cache``, which the runs share. With ``address``, the
cluster's nodes must see OUT at the same path (checked before anything starts).
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
from pathlib import Path
from typing import Callable

from .. import run_folder
from ..config import TrainConfig, setting_items
from ..io_utils import atomic_write_bytes
from . import results as results_table
from .ray_cluster import (Waits, check_reachable, check_resources, check_shared_folder, cluster_cpus, connected,
                          setup_worker, task_error_line)
from .sweep_spec import PlannedRun, SweepSpec

RUNS = "runs"
CACHE = "cache"          # the runs' shared cache: a scene's references, a dataset's triangulated points
OLD_CACHE = "references"  # (its name before the triangulated points joined it: a sweep started then goes on with it)
SPEC = "spec.toml"
RESULTS = ("results.csv", "results.md")
#: What a sweep writes at the top of OUT (claimed in OUT's manifest, as a run claims its outputs)
OUTPUTS = (SPEC, *RESULTS, RUNS, CACHE)


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def differences(a: TrainConfig, b: TrainConfig) -> list[str]:
    """The settings in which two runs differ, beyond how often they checkpoint and evaluate (which do not change
    what a run computes)."""
    a = dataclasses.replace(a, checkpoint_every=b.checkpoint_every, eval_every=b.eval_every)
    return [f"{k} {x!r} -> {y!r}" for (k, x), (_, y) in zip(setting_items(a), setting_items(b)) if x != y]


def finished(run: PlannedRun, folder: Path) -> dict | None:
    """The metrics of ``run`` when its folder holds it finished (the same settings, all its iterations), else None."""
    import json

    try:
        record = run_folder.RunRecord.read(folder, "missing")
        metrics = json.loads((folder / run_folder.METRICS).read_text())
    except (ValueError, OSError):
        return None
    if differences(record.train, run.config) or metrics.get("iterations") != run.config.optim.iterations:
        return None
    return metrics


def train_task(run: PlannedRun, folder: str, cache: str, variant: str) -> dict:
    """A Ray task: ``run`` in ``folder``, resumed from its checkpoint when an earlier attempt left one (the worker
    of that attempt died). Returns its status, metrics and the iteration it resumed at; a failure of the run's own
    is returned as its one-line message (not raised: Ray must not run it again)."""
    from ..errors import one_line
    from ..runs import train_run

    import threading

    from ..runs import Stopped, stopping_on_signals

    setup_worker(variant)
    folder = Path(folder)
    # Ray cancels a running task (the sweep stopped by a signal) by interrupting its main thread as a SIGINT would:
    # with the run's signal handling, the run then finishes its iteration and writes a checkpoint
    stopping = stopping_on_signals() if threading.current_thread() is threading.main_thread() else \
        contextlib.nullcontext()
    try:
        record = None
        if run_folder.holds_run(folder):
            record = run_folder.RunRecord.read(folder, "missing")
            differ = differences(record.train, run.config)
            if differ:
                raise ValueError(f"{folder}: holds a run with other settings ({'; '.join(differ[:3])})")
        with stopping as stop:
            result = train_run(run.dataset, folder, run.config, record, cache=cache, progress=False, log=None,
                               stop=stop)
        return {"status": "done", "metrics": result.metrics, "resumed_at": result.resumed_from}
    except Stopped as e:
        return {"status": "stopped", "step": e.step}
    except (ValueError, OSError, RuntimeError) as e:         # (TrainingDiverged is a RuntimeError)
        return {"status": "failed", "error": one_line(e)}


def _check_folders(spec: SweepSpec, out: Path, overwrite: bool) -> None:
    """Before anything is written: the run folders in OUT hold these runs (or nothing), unless ``overwrite``."""
    for run in spec.runs:
        folder = out / RUNS / run.name
        if overwrite or not (folder / run_folder.CONFIG).exists():
            continue
        try:
            record = run_folder.RunRecord.read(folder, "missing")
        except ValueError as e:
            raise ValueError(f"{e} (--overwrite starts every run again)") from None
        differ = differences(record.train, run.config)
        if differ:
            raise ValueError(f"{folder}: holds a run with other settings than {spec.path} gives it "
                             f"({'; '.join(differ[:3])}{' ...' if len(differ) > 3 else ''}); --overwrite starts every "
                             "run again, or give another output folder")


def _earlier_sweep(out: Path) -> set[str]:
    """The outputs of a sweep of an earlier version of mi-gs (which wrote no manifest) in ``out``, or nothing: its
    spec.toml beside its runs/ and its cache, its results, or a run folder in runs/."""
    if not ((out / SPEC).is_file() and (out / RUNS).is_dir()
            and (any((out / n).exists() for n in (CACHE, OLD_CACHE, *RESULTS))
                 or any((d / run_folder.CONFIG).is_file() for d in (out / RUNS).iterdir()))):
        return set()
    return {n for n in (*OUTPUTS, OLD_CACHE) if (out / n).exists() and not (out / n).is_symlink()}


def check_out(spec: SweepSpec, out: Path, overwrite: bool) -> list[str]:
    """Before anything is written: ``out`` is new, empty, or a sweep's own (its manifest lists what the sweep wrote;
    anything else there is the user's and is neither replaced nor removed), lies in none of the datasets, and, with
    ``overwrite``, no live process holds one of its run folders. Returns what the sweep will claim in ``out``: its
    outputs, but a spec.toml that is the spec itself (``mi-gs sweep OUT/spec.toml -o OUT``), which stays the user's."""
    from ..runs import check_outside_dataset

    for run in spec.runs:
        check_outside_dataset(run.dataset, out)
    manifest = run_folder.Manifest(out)
    if not manifest.entries:
        manifest.entries = _earlier_sweep(out)
    own = [n for n in OUTPUTS if not (n == SPEC and (out / SPEC).exists() and (out / SPEC).samefile(spec.path))]
    try:
        manifest.check_free(own)
    except ValueError as e:
        raise ValueError(f"{e} (a sweep writes into a new or empty folder, or into the folder of an earlier sweep)") \
            from None
    if overwrite:
        for run in spec.runs:
            if (out / RUNS / run.name).is_dir():
                run_folder.RunLock(out / RUNS / run.name).check_free()
    return own


def cache_folder(out: Path) -> Path:
    """OUT/cache, or OUT/references in a sweep started by a version that named it so (its references are kept)."""
    old = out / OLD_CACHE
    return old if old.is_dir() and not (out / CACHE).exists() else out / CACHE


def _prepare(ray, spec: SweepSpec, runs, out: Path, variant: str, progress: bool, log) -> None:
    """What the runs share, made once before they start: the references of the scene files, rendered by Ray workers,
    and the datasets' triangulated initial points, in OUT/cache. A dataset that fails here is left to its runs, which
    record the failure with its message."""
    from ..runs import training_dataset
    from .references import RayFarm

    seen = set()
    workers = max(1, cluster_cpus(ray))
    for run in runs:
        cfg = run.config
        if run.scene_file:
            key = (run.dataset, cfg.scene, cfg.data.seed, cfg.data.test_every)
            cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, init="random", init_points=1))
            farm = RayFarm(run.dataset, cfg.scene.defines, variant, workers=workers)
        elif cfg.data.init in ("auto", "triangulate"):
            key, farm = (run.dataset, cfg.data, cfg.triangulate), None
        else:
            continue
        if key in seen:
            continue
        seen.add(key)
        try:
            training_dataset(run.dataset, cfg, out, cache=str(cache_folder(out)), progress=progress, farm=farm, log=log)
        except (ValueError, OSError, RuntimeError) as e:
            log(f"{run.dataset}: {' '.join(str(e).split())[:300]} (its runs will say so)")


def run_sweep(spec: SweepSpec, out: str | Path, variant: str, address: str | None = None, overwrite: bool = False,
              progress: bool = True, log: Callable[[str], None] = _stderr, waits: Waits = Waits()) -> list[dict]:
    """Every run of ``spec`` in ``out`` (see the module docstring); returns the result rows in the spec's order
    (also written to OUT/results.csv and OUT/results.md). ``waits``: how long to wait for the cluster."""
    from tqdm import tqdm

    out = Path(out)
    _check_folders(spec, out, overwrite)
    own = check_out(spec, out, overwrite)
    if address:
        check_reachable(address, waits.connect)
    with run_folder.RunLock(out):                     # (one sweep per output folder)
        manifest = run_folder.Manifest(out)
        manifest.entries = manifest.entries or _earlier_sweep(out)
        manifest.claim(own)
        if SPEC in own:
            atomic_write_bytes(out / SPEC, spec.path.read_bytes())
        if overwrite:
            for run in spec.runs:
                folder = out / RUNS / run.name
                if folder.is_dir():
                    with run_folder.RunLock(folder):  # (an optimize still running there keeps it: FolderBusy)
                        run_folder.Manifest(folder).remove_outputs()
            for name in RESULTS:
                (out / name).unlink(missing_ok=True)
        rows = {}
        for run in spec.runs:
            metrics = finished(run, out / RUNS / run.name)
            if metrics is not None:
                rows[run.name] = results_table.row(run, "done", metrics)
        todo = [run for run in spec.runs if run.name not in rows]
        if rows:
            log(f"{len(rows)} of {len(spec.runs)} runs finished earlier in {out / RUNS}: not trained again")

        def write():
            results_table.write(out, [rows[r.name] for r in spec.runs if r.name in rows], spec.grid_keys,
                                f"Sweep {spec.path.name}")

        if todo:
            # (after Ray's start: its core puts a handler of its own on SIGTERM that prints a stack and kills the driver)
            with connected(address, connect_seconds=waits.connect) as ray, _stop_requests() as stop:
                check_resources(ray, spec.cpus, spec.gpus, f"{spec.path}: resources")
                if address:
                    check_shared_folder(ray, out, waits.shared_folder)
                _prepare(ray, spec, todo, out, variant, progress, log)
                stop.waiting = True                   # (from here a signal stops the runs at a checkpoint)
                task = ray.remote(max_calls=1)(train_task).options(num_cpus=spec.cpus, num_gpus=spec.gpus,
                                                                  max_retries=spec.retries, retry_exceptions=False)
                cache = str(cache_folder(out))
                refs = {task.remote(run, str(out / RUNS / run.name), cache, variant): run for run in todo}
                bar = tqdm(total=len(spec.runs), initial=len(rows), unit="run", desc="sweep", disable=not progress,
                           dynamic_ncols=True)
                pending = list(refs)
                try:
                    while pending and stop.signum is None:
                        ready, pending = ray.wait(pending, num_returns=1, timeout=WAIT_STEP)
                        for ref in ready:
                            run = refs[ref]
                            rows[run.name] = _collect(ray, ref, run, spec.retries)
                            r = rows[run.name]
                            psnr = "n/a" if r["psnr"] is None else f"{r['psnr']:.2f}"
                            line = (f"{run.name}: PSNR {psnr}" if r["status"] == "done" else   # (kept by --quiet:)
                                    f"mi-gs: warning: {run.name}: {r['status']}: {r['error']}")
                            bar.update(1)
                            if r["status"] == "done":
                                bar.set_postfix(PSNR=psnr, refresh=False)
                            if progress:
                                bar.write(line, file=sys.stderr)
                            else:
                                log(line)
                            write()
                finally:
                    bar.close()
                if stop.signum is not None:
                    _stop_runs(ray, refs, pending, rows, stop.signum, spec.retries, waits.stop)
                    write()
                    raise SweepStopped(stop.signum, [r for r in rows.values() if r["status"] == "stopped"])
        write()
        return [rows[r.name] for r in spec.runs]


#: How often the driver looks up from waiting for the runs (a signal is acted on within this; seconds)
WAIT_STEP = 1.0


class SweepStopped(Exception):
    """The sweep was stopped by a signal: the running runs were asked to checkpoint and stop (``stopped``: their
    result rows); the same command resumes them."""

    def __init__(self, signum: int, stopped: list[dict]):
        self.signum, self.stopped = signum, stopped
        super().__init__(f"stopped by signal {signum}")


@contextlib.contextmanager
def _stop_requests():
    """While the sweep runs, SIGTERM, SIGINT and SIGHUP (Slurm, Kubernetes, Ctrl-C, a closed terminal; also sent to
    the whole process group) ask it to stop: noted for the wait loop, which stops the runs; before the runs start it
    raises :class:`SweepStopped` at once. A second signal ends the process (exit 128 + signal)."""
    import os
    from types import SimpleNamespace

    from ..runs import on_stop_signals

    state = SimpleNamespace(signum=None, waiting=False)

    def handler(signum, frame):
        if state.signum is not None:
            os._exit(128 + signum)
        state.signum = signum
        if not state.waiting:                # (the runs have not started: nothing to checkpoint, stop now)
            raise SweepStopped(signum, [])

    with on_stop_signals(handler):
        yield state


def _stop_runs(ray, refs: dict, pending: list, rows: dict, signum: int, retries: int, seconds: float) -> None:
    """Ask the running runs to checkpoint and stop (Ray interrupts each task as a SIGINT would; the run finishes its
    iteration and writes its checkpoint), wait for them at most ``seconds``, end those still going (each resumes from
    its previous checkpoint), and record
    every run's row (finished meanwhile, stopped, or not started)."""
    import signal

    for ref in pending:
        ray.cancel(ref, force=False)
    ready, late = ray.wait(pending, num_returns=len(pending), timeout=seconds) if pending else ([], [])
    for ref in late:
        ray.cancel(ref, force=True)
    name = signal.Signals(signum).name
    for ref in pending:
        run = refs[ref]
        rows[run.name] = (_collect(ray, ref, run, retries) if ref in ready else
                          results_table.row(run, "stopped", error=f"stopped by {name} (ended after {seconds:g} s); "
                                                                  "run the same command again to resume it"))


def lost_line(ray, e, retries: int) -> str:
    """What happened to a run whose task Ray gave up on, in one line: its node died (the raylet, or the whole
    machine), or its worker process did, ``retries + 1`` times; either way the same command resumes it."""
    again = "run the same command again to resume it from its checkpoint"
    if isinstance(e, (ray.exceptions.LocalRayletDiedError, ray.exceptions.NodeDiedError)):
        return f"the node running it died ({type(e).__name__}); {again}"
    return f"its worker process died {retries + 1} times ({type(e).__name__}); {again}"


def _collect(ray, ref, run: PlannedRun, retries: int) -> dict:
    """The result row of a finished task."""
    try:
        got = ray.get(ref)
    except ray.exceptions.TaskCancelledError:           # (the sweep stopped it: see _stop_runs)
        return results_table.row(run, "stopped", error="stopped before it began; run the same command again")
    except ray.exceptions.RayTaskError as e:           # (a bug, not the run's own failure: recorded as well)
        return results_table.row(run, "failed", error=task_error_line(e))
    except ray.exceptions.RayError as e:
        return results_table.row(run, "failed", error=lost_line(ray, e, retries))
    if got["status"] == "stopped":
        if got["step"] is None:
            return results_table.row(run, "stopped", error="stopped before training began (nothing saved); run the "
                                                            "same command again to start it")
        return results_table.row(run, "stopped", error=f"stopped at iteration {got['step']}; run the same command "
                                                        "again to resume it")
    if got["status"] != "done":
        return results_table.row(run, "failed", error=got["error"])
    return results_table.row(run, "done", got["metrics"], resumed_at=got["resumed_at"])
