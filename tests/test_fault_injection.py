"""Fault injection: ``mi-gs optimize`` killed with SIGKILL again and again, at random moments and while it writes its
checkpoint, resumed each time with ``--resume``. Every resume must succeed, the run must end with the model an
uninterrupted run reaches (test PSNR within 0.5 dB) and no temporary file may survive.

The kills are placed at random checkpoint steps spread over the run (a seeded generator), every other one the moment
a temporary checkpoint file appears, so the test does not depend on the machine's speed. Each restart imports Mitsuba
and loads its kernels from Dr.Jit's cache (about a second on two cores), so the default suite runs a third of the
kills and 12 of the 20 signals, and ``-m slow`` the full counts (24 kills, 20 signals: about 65 s together).
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from mi_gaussians.io_utils import is_temporary_file
from synthetic_dataset import make_blender_dataset
from test_cli import checkpoint_step

EXE = str(Path(sys.executable).parent / "mi-gs")
ITERATIONS = 400
ARGS = ["--iterations", str(ITERATIONS), "--white-background", "--sh-degree", "1", "--checkpoint-every", "2",
        "--eval-every", "0", "--quiet", "--random-points", "3000"]


def temporary_files(out: Path) -> list[Path]:
    return [p for p in out.rglob("*") if is_temporary_file(p.name)]


def _start(data: Path, out: Path, resume: bool) -> subprocess.Popen:
    """The run (or its resume), its stderr going to a file (a pipe nobody reads while it runs could fill up)."""
    cmd = [EXE, "optimize", str(data), "-o", str(out), *ARGS] + (["--resume"] if resume else [])
    log = open(out.parent / "stderr.txt", "wb")
    try:
        return subprocess.Popen(cmd, cwd=tempfile.gettempdir(), stdout=subprocess.DEVNULL, stderr=log)
    finally:
        log.close()


def _stderr(out: Path) -> str:
    return (out.parent / "stderr.txt").read_text(errors="replace")[-3000:]


def _kill_while_writing(proc: subprocess.Popen, out: Path, deadline: float) -> bool:
    """Poll the checkpoint folder and kill as soon as a temporary checkpoint appears; True if one was seen."""
    folder = out / "checkpoints"
    while time.time() < deadline and proc.poll() is None:
        if folder.is_dir() and any(is_temporary_file(n) for n in os.listdir(folder)):
            proc.send_signal(signal.SIGKILL)
            return True
        time.sleep(0.0005)
    proc.send_signal(signal.SIGKILL)
    return False


def _finished_like_an_uninterrupted_run(data: Path, out: Path, straight: Path, args: list[str],
                                       iterations: int) -> str:
    """The interrupted-and-resumed run in ``out`` finished all ``iterations`` with no temporary file left, and its
    test PSNR is within 0.5 dB of the same run trained without interruption in ``straight``; both PSNRs, as text."""
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == iterations
    assert not temporary_files(out), temporary_files(out)
    res = subprocess.run([EXE, "optimize", str(data), "-o", str(straight), *args],
                         cwd=tempfile.gettempdir(), capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    other = json.loads((straight / "metrics.json").read_text())
    assert abs(metrics["mean"]["psnr"] - other["mean"]["psnr"]) < 0.5, (metrics["mean"], other["mean"])
    return f"{metrics['mean']['psnr']:.2f} against {other['mean']['psnr']:.2f} uninterrupted"


@pytest.mark.parametrize("kills_asked", [8, pytest.param(24, marks=pytest.mark.slow)])
def test_kill_9_at_random_moments_then_resume(tmp_path, kills_asked):
    data = make_blender_dataset(tmp_path / "scene", n_train=12, n_test=3, size=48)
    out = tmp_path / "killed"
    rng = random.Random(1)
    kills, mid_write, resumes, steps = 0, 0, 0, []
    proc = _start(data, out, resume=False)
    while True:
        if kills >= kills_asked:                 # enough: let the last resume finish
            proc.wait(timeout=900)
            assert proc.returncode == 0, _stderr(out)
            break
        # a random checkpoint step ahead of the last one, spread so that the kills cover the whole run
        current = checkpoint_step(out)
        room = max(2, (ITERATIONS - 40 - current) * 2 // (kills_asked - kills))
        target = min(current + rng.randint(1, room), ITERATIONS - 40)
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None and checkpoint_step(out) < target:
            time.sleep(0.005)
        if proc.poll() is not None:              # finished before the kill: the run is complete
            assert proc.returncode == 0, _stderr(out)
            break
        if kills % 2:
            saw = _kill_while_writing(proc, out, time.time() + 30)
        else:
            time.sleep(rng.uniform(0.0, 0.02))
            proc.send_signal(signal.SIGKILL)
            saw = False
        proc.wait()
        if proc.returncode != -signal.SIGKILL:   # it ended on its own before the signal arrived
            assert proc.returncode == 0, _stderr(out)
            break
        kills += 1
        mid_write += bool(saw and temporary_files(out))
        steps.append(checkpoint_step(out))
        proc = _start(data, out, resume=True)
        resumes += 1

    assert kills >= kills_asked * 5 // 6, f"only {kills} kills before the run finished (checkpoint steps {steps})"
    assert mid_write >= 1, "no kill landed while a checkpoint was being written"
    assert steps == sorted(steps), f"a resume went back: {steps}"
    assert steps[-1] > ITERATIONS // 2, f"the kills did not cover the run: {steps}"
    assert not (out / ".mi-gs.lock").exists() or (out / ".mi-gs.lock").read_text().strip() == ""
    psnr = _finished_like_an_uninterrupted_run(data, out, tmp_path / "straight", ARGS, ITERATIONS)
    print(f"{kills} kills ({mid_write} during a checkpoint write), {resumes} resumes; checkpoint steps {steps}; "
          f"PSNR {psnr}")


TERM_ITERATIONS = 1200
TERM_ARGS = ["--iterations", str(TERM_ITERATIONS), "--white-background", "--sh-degree", "1", "--checkpoint-every",
             "10", "--eval-every", "0", "--quiet", "--random-points", "3000"]


@pytest.mark.parametrize("terms", [12, pytest.param(20, marks=pytest.mark.slow)])
def test_sigterm_at_random_moments_checkpoints_and_resumes(tmp_path, terms):
    """SIGTERM (what Slurm, Kubernetes and Ray send) at random moments (12 in the default suite, 20 with ``-m
    slow``), before and during training: each time the run stops with status 143 and one line (during training: the
    iteration, saved in a checkpoint, and the --resume command), and the next start continues from exactly there;
    once, a second SIGTERM right after the first ends it at once. A signal that lands while the interpreter is still
    importing (before mi-gs can handle it) ends the process as the default action does, with nothing written yet
    (also when a thread other than the main one takes it during pycolmap's import, after glog's stack trace); a run
    that does not end within 120 s of its signal fails the test at once. The final model is within 0.5 dB of an
    uninterrupted run's, and no temporary file survives."""
    data = make_blender_dataset(tmp_path / "scene", n_train=12, n_test=3, size=48)
    out = tmp_path / "termed"
    rng = random.Random(7)
    stopped_at, before_training, importing, signals = [], 0, 0, 0

    def start():
        resume = (out / "checkpoints" / "ckpt.npz").is_file()
        cmd = [EXE, "optimize", str(data), "-o", str(out), *TERM_ARGS] + (["--resume"] if resume else [])
        log = open(tmp_path / "stderr.txt", "wb")
        try:
            return subprocess.Popen(cmd, cwd=tempfile.gettempdir(), stdout=subprocess.DEVNULL, stderr=log)
        finally:
            log.close()

    while signals < terms:
        proc = start()
        if signals % 4 == 0:                              # early: while starting, before training
            time.sleep(rng.uniform(0.2, 0.9))
        else:                                             # during training: a random iteration ahead
            current = checkpoint_step(out)
            room = max(20, (TERM_ITERATIONS - 60 - current) * 2 // (terms - signals))
            target = min(current + rng.randint(10, room), TERM_ITERATIONS - 60)
            deadline = time.time() + 300
            while time.time() < deadline and proc.poll() is None and checkpoint_step(out) < target:
                time.sleep(0.002)
            time.sleep(rng.uniform(0.0, 0.02))
        assert proc.poll() is None, "the run ended before its signal"
        proc.send_signal(signal.SIGTERM)
        if signals == terms // 2 + 1:
            time.sleep(0.003)
            proc.send_signal(signal.SIGTERM)              # a second signal: at once
        _wait_or_fail(proc, 120, tmp_path / "stderr.txt")
        err = (tmp_path / "stderr.txt").read_text(errors="replace").strip()
        signals += 1
        if proc.returncode == -signal.SIGTERM and (not err or _in_pycolmaps_import(err)):   # (still importing)
            importing += 1
            continue
        if signals == terms // 2 + 2:                     # (the second signal may cut the line short, or come
            assert proc.returncode in (143, -signal.SIGTERM), (proc.returncode, err[-2000:])   # after the run had
            continue                                      # stopped and put the default action back)
        assert proc.returncode == 143, (proc.returncode, err[-2000:])
        last = err.splitlines()[-1] if err else ""
        if "before training began" in last:
            before_training += 1
            continue
        assert last.startswith("mi-gs: stopped by SIGTERM at iteration ") and "--resume" in last, err[-2000:]
        step = int(last.split("at iteration ")[1].split(",")[0])
        assert checkpoint_step(out) == step, (checkpoint_step(out), step)     # saved exactly there
        assert not stopped_at or step >= stopped_at[-1]
        stopped_at.append(step)
    proc = start()
    proc.wait(timeout=600)
    assert proc.returncode == 0, (tmp_path / "stderr.txt").read_text()[-2000:]
    assert before_training + importing >= 2 and len(stopped_at) >= terms // 2, (before_training, importing, stopped_at)
    assert any(s % 10 for s in stopped_at), stopped_at                # (not only the periodic checkpoints)
    psnr = _finished_like_an_uninterrupted_run(data, out, tmp_path / "straight", TERM_ARGS, TERM_ITERATIONS)
    print(f"{signals} SIGTERMs ({importing} while importing, {before_training} before training); stopped at "
          f"{stopped_at}; PSNR {psnr}")


SIGNAL_DURING_IMPORT = """
import signal, sys, threading
import mi_gaussians.runs as runs
assert "pycolmap" not in sys.modules


class SignalBeforePycolmap:
    # (a finder that sends the main thread SIGTERM as pycolmap's import begins, and then lets the import go on)
    def find_spec(self, name, path=None, target=None):
        if name == "pycolmap":
            signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
        return None


sys.meta_path.insert(0, SignalBeforePycolmap())
got = []
try:
    with runs.on_stop_signals(lambda signum, frame: got.append(signum) or (_ for _ in ()).throw(KeyboardInterrupt)):
        print("inside the block", flush=True)
except KeyboardInterrupt:
    pass
print("handled", got, signal.getsignal(signal.SIGTERM) == signal.SIG_DFL, flush=True)
"""


def test_a_signal_during_pycolmaps_import_waits_for_our_handler(tmp_path):
    """pycolmap's import puts glog's failure handler on SIGTERM (not async-signal-safe: one that reached it inside
    malloc deadlocked, and the run never ended). From before that import until mi-gs's handler is in place the stop
    signals are blocked: one sent meanwhile reaches our handler, before the block's body, and the handlers before
    are put back afterwards."""
    proc = subprocess.run([sys.executable, "-c", SIGNAL_DURING_IMPORT], capture_output=True, text=True, timeout=120,
                          cwd=tempfile.gettempdir())
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert proc.stdout.splitlines() == [f"handled [{int(signal.SIGTERM)}] True"], proc.stdout


def _wait_or_fail(proc, seconds: float, stderr: Path) -> None:
    """Wait for a signalled run to end; one that has not ended within ``seconds`` (a step and a checkpoint take well
    under one) hangs: kill it and fail with what it printed."""
    try:
        proc.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=30)
        pytest.fail(f"the run did not end within {seconds} s of its SIGTERM: "
                    f"{stderr.read_text(errors='replace')[-2000:]}")


def _in_pycolmaps_import(err: str) -> bool:
    """Whether ``err`` is all that glog's handler prints when a SIGTERM lands while pycolmap is being imported (it puts
    that handler on SIGTERM as its import begins, before mi-gs can put its own back): a stack trace inside
    pycolmap, and the process ended as the default action ends it, before anything was written."""
    lines = err.splitlines()
    return (lines[0].startswith("*** Aborted at") and any(line.startswith("*** SIGTERM") for line in lines)
            and "pycolmap" in err and not any(line.startswith("mi-gs") for line in lines))


def test_sigterm_after_pycolmap_was_imported_checkpoints(tmp_path):
    """pycolmap, imported once the run has begun (to triangulate the initial points of a Blender layout, to read a
    COLMAP model, to undistort), puts glog's handler on SIGTERM, one that prints a stack trace and kills the process:
    the run's own handler must still be the one that answers (a checkpoint, one line, status 143)."""
    data = make_blender_dataset(tmp_path / "scene", n_train=8, n_test=2, size=48)
    out = tmp_path / "run"
    cmd = [EXE, "optimize", str(data), "-o", str(out), "--iterations", "20000", "--checkpoint-every", "10",
           "--eval-every", "0", "--quiet", "--init", "auto", "--random-points", "3000"]
    with open(tmp_path / "stderr.txt", "wb") as log:
        proc = subprocess.Popen(cmd, cwd=tempfile.gettempdir(), stdout=subprocess.DEVNULL, stderr=log)
    try:
        deadline = time.time() + 180
        while time.time() < deadline and proc.poll() is None and checkpoint_step(out) < 30:
            time.sleep(0.01)
        assert proc.poll() is None, _stderr(out)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = _stderr(out)
    assert proc.returncode == 143 and "Aborted at" not in err, (proc.returncode, err)
    last = err.strip().splitlines()[-1]
    assert last.startswith("mi-gs: stopped by SIGTERM at iteration "), err
    assert checkpoint_step(out) == int(last.split("at iteration ")[1].split(",")[0])


def test_a_stop_while_the_outputs_are_written_stops_at_the_last_iteration(tmp_path):
    """A signal that arrives after the last iteration, while the model is evaluated and written, stops the run there
    (its checkpoint is the last iteration's, no metrics.json yet); --resume writes the outputs without training."""
    import dataclasses

    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from mi_gaussians.optim.trainer import Trainer, TrainingStopped
    from test_train import load, small_config

    data = make_blender_dataset(tmp_path / "scene", n_train=6, n_test=2, size=32)
    cfg = small_config(20)
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, random_points=500))
    tr = Trainer(load(data, cfg), cfg, tmp_path / "run", progress=False)

    def monitor(t):
        if t.step == cfg.optim.iterations:
            t.stop_signal = signal.SIGTERM                 # (after the last iteration: what finish() does next)

    try:
        tr.run(monitor=monitor)
    except TrainingStopped as e:
        assert e.step == cfg.optim.iterations
    else:
        raise AssertionError("the stop was ignored")
    assert checkpoint_step(tmp_path / "run") == cfg.optim.iterations
    assert not (tmp_path / "run" / "metrics.json").exists()
    resumed = Trainer(load(data, cfg), cfg, tmp_path / "run", progress=False)
    metrics = resumed.run(resume=True)
    assert resumed.resumed_from == cfg.optim.iterations and metrics["iterations"] == cfg.optim.iterations
