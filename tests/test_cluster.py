"""Beyond one process, on a local Ray cluster (``conftest.ray_cluster``: 2 CPUs, started once, shut down at the end):
``mi-gs sweep`` (a 2 x 2 sweep, a second run that trains nothing, a worker killed mid-run that resumes from its
checkpoint, a run failing for its own reason), references rendered by Ray workers equal to a single process's bit for
bit, the spec's one-line errors, and that importing mi_gaussians imports no Ray."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from mi_gaussians.cluster.sweep_spec import read_spec
from test_cli import assert_one_line_error, checkpoint_step, run

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
EXE = str(Path(sys.executable).parent / "mi-gs")


def write_spec(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def rows(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


def files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


SPEC = """datasets = ["{a}", "{b}"]
iterations = 60
[set]
"data.random_points" = 500
eval_every = 0
[grid]
strategy = ["default", "mcmc"]
"""


def test_sweep_of_two_datasets_by_two_settings_and_again(ray_cluster, tmp_path):
    spec = write_spec(tmp_path / "spec.toml", SPEC.format(a=DATA / "tiny_blender", b=DATA / "tiny_colmap"))
    out = tmp_path / "out"
    r = run("sweep", spec, "-o", out, "--address", ray_cluster, "--quiet")
    assert r.returncode == 0, r.stderr
    got = rows(out)
    assert [(x["dataset"], x["strategy"], x["status"]) for x in got] == [
        ("tiny_blender", "default", "done"), ("tiny_blender", "mcmc", "done"),
        ("tiny_colmap", "default", "done"), ("tiny_colmap", "mcmc", "done")]
    assert all(float(x["psnr"]) > 0 and int(x["gaussians"]) > 0 for x in got)
    md = (out / "results.md").read_text()
    assert "| default | 2 of 2 |" in md and "| mcmc | 2 of 2 |" in md          # the mean per setting
    for x in got:                                  # ordinary run folders, with the run's own settings
        record = json.loads((out / "runs" / x["run"] / "config.json").read_text())
        assert record["train"]["strategy"] == x["strategy"] and record["train"]["optim"]["iterations"] == 60
    e = run("eval", out / "runs" / got[0]["run"])
    assert e.returncode == 0, e.stderr
    # the same sweep again: every run is finished, nothing is trained or written
    before = files(out / "runs")
    again = run("sweep", spec, "-o", out, "--address", ray_cluster)        # (not --quiet: the line below is information)
    assert again.returncode == 0, again.stderr
    assert "4 of 4 runs finished earlier" in again.stderr and files(out / "runs") == before
    assert [x["psnr"] for x in rows(out)] == [x["psnr"] for x in got]
    # the spec changed under the same OUT: refused before anything starts, nothing touched
    write_spec(spec, SPEC.format(a=DATA / "tiny_blender", b=DATA / "tiny_colmap").replace("= 60", "= 70"))
    assert_one_line_error(run("sweep", spec, "-o", out, "--address", ray_cluster), "holds a run with other settings",
                          "optim.iterations 60 -> 70")
    assert files(out / "runs") == before


@pytest.fixture(scope="module")
def larger(tmp_path_factory):
    """A dataset that trains long enough to kill its worker mid-run (256 x 256, about 10 s on one thread)."""
    import mitsuba as mi  # noqa: F401
    from synthetic_dataset import make_blender_dataset

    return make_blender_dataset(tmp_path_factory.mktemp("larger") / "synth", size=256, n_train=8, n_test=2)


KILL_SPEC = """datasets = ["{data}"]
iterations = 800
[set]
"data.random_points" = 3000
"data.background" = [1, 1, 1]
"optim.sh_degree" = 1
eval_every = 0
checkpoint_every = 50
"""


def _sweep(spec: Path, out: Path, address: str) -> subprocess.Popen:
    log = open(out.parent / f"{out.name}.stderr", "wb")
    try:
        return subprocess.Popen([EXE, "sweep", str(spec), "-o", str(out), "--address", address, "--quiet"],
                                cwd=tempfile.gettempdir(), stdout=subprocess.DEVNULL, stderr=log)
    finally:
        log.close()


@pytest.mark.slow   # (two 800-iteration sweeps through Ray, one killed and retried: two minutes and more on 2 cores)
def test_a_killed_worker_is_retried_and_resumes_from_its_checkpoint(ray_cluster, larger, tmp_path):
    """The worker training a run is killed (SIGKILL) once the run has checkpointed: Ray runs the task again, which
    resumes at the checkpoint's iteration and ends within 0.5 dB of the same run never interrupted."""
    spec = write_spec(tmp_path / "spec.toml", KILL_SPEC.format(data=larger))
    killed, whole = tmp_path / "killed", tmp_path / "whole"
    procs = [_sweep(spec, killed, ray_cluster), _sweep(spec, whole, ray_cluster)]
    try:
        folder = killed / "runs" / "synth-s0"
        deadline = time.monotonic() + 240
        while checkpoint_step(folder) < 150:
            assert time.monotonic() < deadline, "the run did not checkpoint in time"
            assert procs[0].poll() is None, (killed.parent / "killed.stderr").read_text()[-2000:]
            time.sleep(0.05)
        pid = int((folder / ".mi-gs.lock").read_text().split()[0])
        assert pid != os.getpid()
        os.kill(pid, signal.SIGKILL)
        at_kill = checkpoint_step(folder)            # (the worker is gone: this is what the retry resumes from)
        for p in procs:
            p.wait(timeout=300)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert [p.returncode for p in procs] == [0, 0], (tmp_path / "killed.stderr").read_text()[-2000:]
    (k,), (w,) = rows(killed), rows(whole)
    assert k["status"] == w["status"] == "done" and w["resumed_at"] == ""
    assert int(k["resumed_at"]) == at_kill and 150 <= at_kill < 800
    assert abs(float(k["psnr"]) - float(w["psnr"])) < 0.5, (k["psnr"], w["psnr"])
    assert json.loads((folder / "metrics.json").read_text())["iterations"] == 800


def test_a_sweep_stopped_by_a_signal_checkpoints_its_runs_and_resumes(ray_cluster, larger, tmp_path):
    """SIGTERM to the sweep's process group (as Slurm and Kubernetes send it): the driver asks the running run to
    checkpoint and stop, exits 143 with one line within the bound, no worker trains on, and the same command resumes
    the run from that checkpoint."""
    from mi_gaussians.run_folder import RunLock

    stop_s = 40
    spec = write_spec(tmp_path / "spec.toml", KILL_SPEC.format(data=larger))
    out = tmp_path / "out"
    log = open(tmp_path / "sweep.stderr", "wb")
    proc = subprocess.Popen([EXE, "sweep", str(spec), "-o", str(out), "--address", ray_cluster, "--quiet",
                             "--stop-timeout", str(stop_s)],
                            cwd=tempfile.gettempdir(), stdout=subprocess.DEVNULL, stderr=log, start_new_session=True)
    log.close()
    folder = out / "runs" / "synth-s0"
    try:
        deadline = time.monotonic() + 240
        while checkpoint_step(folder) < 50:                       # (the first checkpoint: most of the run ahead)
            assert time.monotonic() < deadline, "the run did not checkpoint in time"
            assert proc.poll() is None, (tmp_path / "sweep.stderr").read_text()[-2000:]
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGTERM)
        t0 = time.monotonic()
        proc.wait(timeout=stop_s + 60)
        assert time.monotonic() - t0 < stop_s + 30
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    err = (tmp_path / "sweep.stderr").read_text()
    assert proc.returncode == 143, err[-2000:]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines[-1].startswith("mi-gs: sweep stopped by SIGTERM: 1 run stopped at a checkpoint"), err[-2000:]
    assert "Traceback" not in err and "\x1b[" not in err                       # (no colour codes, no stack)
    (row,) = rows(out)
    assert row["status"] == "stopped" and "run the same command again" in row["error"]
    stopped_at = checkpoint_step(folder)
    assert 50 <= stopped_at < 800 and f"stopped at iteration {stopped_at}" in row["error"]
    RunLock(folder).check_free()                                  # no worker trains on (it would hold the lock)
    assert checkpoint_step(folder) == stopped_at and not (folder / "metrics.json").exists()
    again = run("sweep", spec, "-o", out, "--address", ray_cluster, "--quiet")
    assert again.returncode == 0, again.stderr
    (row,) = rows(out)
    assert row["status"] == "done" and int(row["resumed_at"]) == stopped_at


def test_a_run_failing_for_its_own_reason_is_recorded_and_the_others_finish(ray_cluster, tmp_path):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(DATA / "tiny_blender", broken)
    image = next((broken / "train").glob("*.png"))
    image.write_bytes(image.read_bytes()[:60])                  # a truncated PNG
    spec = write_spec(tmp_path / "spec.toml", f'datasets = ["{broken}", "{DATA / "tiny_blender"}"]\niterations = 30\n'
                                              '[set]\n"data.random_points" = 300\neval_every = 0\n')
    out = tmp_path / "out"
    r = run("sweep", spec, "-o", out, "--address", ray_cluster, "--quiet")
    assert r.returncode == 1, r.stderr                          # (finished, with a failed run)
    bad, good = rows(out)
    assert bad["status"] == "failed" and image.name in bad["error"] and "\n" not in bad["error"]
    assert good["status"] == "done" and "failed" in (out / "results.md").read_text()
    said = [ln for ln in r.stderr.splitlines() if ln.strip()]      # --quiet: the failure is said, nothing else
    assert len(said) == 1 and said[0].startswith(f"mi-gs: warning: {bad['run']}: failed: "), r.stderr


def test_distributed_references_equal_single_process_ones(ray_cluster, tmp_path):
    """``mi-gs optimize scene.xml --workers 2``: the references rendered by two Ray workers (each loading the scene
    once, with its -D values) are the files one process renders, bit for bit (images and depths)."""
    from mi_gaussians.config import SceneConfig
    from mi_gaussians.data.scene_dataset import load_scene_dataset
    from test_mitsuba_scene import write_scene

    scene = write_scene(tmp_path / "scene.xml", w=24, h=24, spp=4, sky="$sky")
    scene.write_text(scene.read_text().replace("<sensor", '<default name="sky" value="0.2"/><sensor', 1))
    r = run("optimize", scene, "-o", tmp_path / "run", "--workers", "2", "--address", ray_cluster, "--iterations", 5,
            "--views", 5, "--test-views", 2, "-D", "sky=0.6", "--init", "random", "--init-points", 200)
    assert r.returncode == 0, r.stderr
    assert "on 2 Ray workers" in r.stderr
    (farmed,) = (tmp_path / "run" / "references").iterdir()
    cfg = SceneConfig(views=5, test_views=2, defines=("sky=0.6",), init="random", init_points=200)
    ds = load_scene_dataset(scene, cfg, cache_root=tmp_path / "local", progress=False)
    assert ds.references.name == farmed.name                    # the same key: the same scene, rig and settings
    local = sorted(p.relative_to(ds.references) for p in ds.references.rglob("*") if p.suffix in (".exr", ".npy"))
    assert len(local) == 14 and local == sorted(p.relative_to(farmed) for p in farmed.rglob("*")
                                                if p.suffix in (".exr", ".npy"))
    from mi_gaussians.data.images import read_image

    for rel in local:
        a, b = ds.references / rel, farmed / rel
        if rel.suffix == ".npy":
            assert np.array_equal(np.load(a), np.load(b)), rel
        else:
            assert np.array_equal(read_image(a), read_image(b)), rel


def test_shared_folder_check(ray_cluster, tmp_path, monkeypatch):
    import ray

    from mi_gaussians.cluster import ray_cluster as rc

    rc.check_shared_folder(ray, tmp_path / "seen")                 # one node, the same file system: fine
    assert not any((tmp_path / "seen").iterdir())                   # (its token removed)
    monkeypatch.setattr(rc, "_sees", lambda path, token: (False, "elsewhere"))
    with pytest.raises(ValueError) as e:
        rc.check_shared_folder(ray, tmp_path / "seen")
    assert "not seen by 1 of the cluster's 1 nodes: elsewhere" in str(e.value) and "\n" not in str(e.value)


# ------------------------------------------------------------------------------------------ specs, no cluster needed
@pytest.mark.parametrize("text, words", [
    ("datasets = []", "datasets: expected a non-empty list"),
    ('datasets = ["nowhere/*"]', "datasets[0]: 'nowhere/*' matches nothing"),
    ('datasets = ["missing"]', "datasets[0]:"),
    ('datasets = ["{a}"]\nnope = 1', "nope: not a key of a sweep spec"),
    ('datasets = ["{a}"]\niterations = "300"', "iterations: expected a positive integer"),
    ('datasets = ["{a}"]\nseeds = [0, 0]', "seeds: expected a list of different integers"),
    ('datasets = ["{a}"]\n[grid]\nstrategy = []', "grid.strategy: expected a non-empty list"),
    ('datasets = ["{a}"]\n[grid]\nstrategy = ["default", "sgd"]', "grid.strategy: 'sgd' is not one of default, mcmc"),
    ('datasets = ["{a}"]\n[set]\n"densify.nope" = 1', "set.densify.nope: no such field"),
    ('datasets = ["{a}"]\n[set]\n"mcmc.cap_max" = 10\n[grid]\nstrategy = ["default", "mcmc"]',
     "set.mcmc.cap_max: the mcmc section configures --strategy mcmc, not the default strategy"),
    ('datasets = ["{a}"]\n[set]\nstrategy = "mcmc"\n[grid]\nstrategy = ["default"]', "set.strategy: is also in [grid]"),
    ('datasets = ["{a}"]\n[resources]\ncpus = 0', "resources.cpus: expected a whole number >= 1, or a fraction"),
    ('datasets = ["{a}"]\n[resources]\ncpus = inf', "resources.cpus: expected a whole number >= 1"),
    ('datasets = ["{a}"]\n[resources]\ncpus = nan', "resources.cpus: expected a whole number >= 1"),
    ('datasets = ["{a}"]\n[resources]\ncpus = 0.00001', "in steps of 0.0001, got 1e-05"),
    ('datasets = ["{a}"]\n[resources]\ncpus = 1.5', "resources.cpus: expected a whole number >= 1"),
    ('datasets = ["{a}"]\n[resources]\ngpus = -1', "resources.gpus: expected a whole number >= 0"),
    ('datasets = ["{a}"]\nseeds = [0, 1]\n[set]\nseed = 3', "set.seed: a run's seed comes from the spec's seeds"),
    ('datasets = ["{a}"]\n[set]\n"data.seed" = 3', "set.data.seed: a run's seed comes from the spec's seeds"),
    ('datasets = ["{a}"]\n[grid]\nseed = [1, 2]', "grid.seed: a run's seed comes from the spec's seeds"),
    ('datasets = ["{a}"]\niterations = 300\n[set]\n"optim.iterations" = 500',
     "set.optim.iterations: give the number of iterations as the spec's iterations = N"),
    ('datasets = ["{a}"]\n[grid]\n"optim.iterations" = [100, 200]', "grid.optim.iterations: give the number"),
    ('datasets = ["{notdata}"]', "datasets[0]: {notdata}: unknown dataset layout"),
    ('datasets = ["{empty}"]', "empty folder, not a dataset"),
    ('datasets = ["{a}"]\n[resources]\nram = 2', "resources.ram: not a resource"),
    ('datasets = ["{a}"', "not valid TOML"),
])
def test_bad_specs_are_one_line_naming_the_key(tmp_path, text, words):
    (tmp_path / "notdata").mkdir()
    (tmp_path / "notdata" / "photo.jpg").write_bytes(b"not a dataset")
    (tmp_path / "empty").mkdir()
    fill = {"{a}": str(DATA / "tiny_blender"), "{notdata}": str(tmp_path / "notdata"), "{empty}": str(tmp_path / "empty")}
    for k, v in fill.items():
        text, words = text.replace(k, v), words.replace(k, v)
    spec = write_spec(tmp_path / "spec.toml", text)
    with pytest.raises(ValueError) as e:
        read_spec(spec)
    assert words in str(e.value) and str(spec) in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_fractional_and_whole_resources_are_taken(tmp_path):
    for cpus, gpus in ((0.5, 0), (2, 0.25), (1, 1), (0.0001, 0.5)):
        spec = write_spec(tmp_path / "spec.toml", f'datasets = ["{DATA / "tiny_blender"}"]\n[resources]\n'
                                                  f"cpus = {cpus}\ngpus = {gpus}\n")
        got = read_spec(spec)
        assert (got.cpus, got.gpus) == (cpus, gpus)


def test_a_spec_that_is_not_utf8_is_named(tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_bytes(b'datasets = ["caf\xe9"]\n')
    with pytest.raises(ValueError, match=r"spec\.toml: not UTF-8 text"):
        read_spec(spec)
    assert_one_line_error(run("sweep", spec, "-o", tmp_path / "out"), "not UTF-8 text")
    assert not (tmp_path / "out").exists()


def test_bad_spec_through_the_command_line_writes_nothing(tmp_path):
    spec = write_spec(tmp_path / "spec.toml", 'datasets = ["nowhere"]')
    assert_one_line_error(run("sweep", spec, "-o", tmp_path / "out"), "datasets[0]")
    assert not (tmp_path / "out").exists()


def test_spec_plans_every_combination_with_relative_paths_and_globs(tmp_path):
    import shutil

    for name in ("a", "b"):
        shutil.copytree(DATA / "tiny_blender", tmp_path / "data" / name / "tiny")
    spec = write_spec(tmp_path / "specs" / "s.toml", 'datasets = ["../data/*/tiny", "../data/a/tiny"]\n'
                                                     'iterations = 500\nseeds = [0, 1]\n[set]\n'
                                                     '"data.resolution" = 2\n[grid]\nstrategy = ["default", "mcmc"]\n'
                                                     '"optim.sh_degree" = [1, 3]\n')
    s = read_spec(spec)
    assert [r.name for r in s.runs][:4] == ["a_tiny-default_1-s0", "a_tiny-default_1-s1", "a_tiny-default_3-s0",
                                            "a_tiny-default_3-s1"]
    assert len(s.runs) == 2 * 4 * 2 and len({r.name for r in s.runs}) == 16       # (the repeated dataset once)
    r = s.runs[-1]
    assert (r.label, r.setting, r.seed) == ("b_tiny", (("strategy", "mcmc"), ("optim.sh_degree", 3)), 1)
    c = r.config
    assert (c.strategy, c.optim.sh_degree, c.data.resolution, c.seed, c.data.seed) == ("mcmc", 3, 2, 1, 1)
    assert c.optim.iterations == 500 and c.densify.densify_until_iter == 250          # the paper's proportions
    assert (s.cpus, s.gpus, s.retries) == (1.0, 0.0, 3) and read_spec(spec, cuda=True).gpus == 1.0


def test_importing_the_package_or_the_command_line_imports_no_ray():
    code = ("import sys, mitsuba as mi; mi.set_variant('llvm_ad_rgb'); import mi_gaussians; "
            "from mi_gaussians.cli import build_parser; build_parser(); import mi_gaussians.cluster.sweep; "
            "print('ray' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr


def test_without_ray_the_error_names_the_extra(tmp_path):
    code = ("import sys; sys.modules['ray'] = None; from mi_gaussians.cli import main; "
            f"sys.exit(main(['sweep', {str(tmp_path / 's.toml')!r}, '-o', {str(tmp_path / 'o')!r}]))")
    write_spec(tmp_path / "s.toml", f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 5\n')
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert_one_line_error(r, "needs Ray", "pip install 'mi-gaussians[ray]'")


def test_a_sweep_started_before_the_cache_was_renamed_keeps_its_references(tmp_path):
    from mi_gaussians.cluster.sweep import cache_folder

    assert cache_folder(tmp_path) == tmp_path / "cache"
    (tmp_path / "references").mkdir()                              # (a sweep of the version that named it so)
    assert cache_folder(tmp_path) == tmp_path / "references"
    (tmp_path / "cache").mkdir()
    assert cache_folder(tmp_path) == tmp_path / "cache"


# ------------------------------------------------------------------------- what a sweep may write, and where (no Ray)
def tree(folder: Path) -> dict:
    """Every file below ``folder`` with its bytes (what a refused command must leave as it was)."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_sweep_refuses_a_folder_of_the_users(tmp_path):
    """A folder that is neither new, nor empty, nor a sweep's: refused in one line before anything is written (the
    user's spec.toml and results.csv there were replaced without a word before)."""
    spec = write_spec(tmp_path / "s.toml", f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 5\n')
    out = tmp_path / "mine"
    write_spec(out / "spec.toml", "# my own notes\n")
    (out / "results.csv").write_text("my,numbers\n1,2\n")
    before = tree(out)
    assert_one_line_error(run("sweep", spec, "-o", out), f"{out / 'spec.toml'}: exists and was not written by mi-gs",
                          "a new or empty folder")
    assert tree(out) == before and sorted(p.name for p in out.iterdir()) == ["results.csv", "spec.toml"]


def test_a_sweep_folder_may_hold_its_own_spec_and_an_earlier_sweeps_outputs(tmp_path):
    from mi_gaussians.cluster.sweep import OUTPUTS, SPEC, check_out

    out = tmp_path / "sweep"
    spec_path = write_spec(out / "spec.toml", f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 5\n')
    spec = read_spec(spec_path)
    # mi-gs sweep OUT/spec.toml -o OUT: the spec stays the user's (not claimed, not rewritten), the rest is the sweep's
    assert check_out(spec, out, overwrite=False) == [n for n in OUTPUTS if n != SPEC]
    # a sweep of an earlier version (no manifest): its spec.toml, runs/ and cache/ are its own
    old = tmp_path / "old"
    write_spec(old / "spec.toml", "# the spec of that sweep\n")
    (old / "runs").mkdir()
    (old / "cache").mkdir()
    assert check_out(spec, old, overwrite=False) == list(OUTPUTS)
    # ... also one stopped before any run finished, with no cache: a run folder in runs/ is enough
    (old / "cache").rmdir()
    (old / "runs" / "a-s0").mkdir(parents=True)
    (old / "runs" / "a-s0" / "config.json").write_text("{}")
    assert check_out(spec, old, overwrite=False) == list(OUTPUTS)
    # ... but not without its runs: then spec.toml is somebody's file
    import shutil

    shutil.rmtree(old / "runs")
    with pytest.raises(ValueError, match="exists and was not written by mi-gs"):
        check_out(spec, old, overwrite=False)


def test_a_sweep_output_inside_a_dataset_is_refused(tmp_path):
    import shutil

    data = tmp_path / "tiny_blender"
    shutil.copytree(DATA / "tiny_blender", data)
    spec = write_spec(tmp_path / "s.toml", f'datasets = ["{data}"]\niterations = 5\n')
    before = tree(data)
    assert_one_line_error(run("sweep", spec, "-o", data / "sweep"), "lies in the dataset folder", str(data))
    assert tree(data) == before and not (data / "sweep").exists()


def test_a_cache_inside_the_dataset_is_refused(tmp_path):
    import shutil

    data = tmp_path / "tiny_colmap"
    shutil.copytree(DATA / "tiny_colmap", data)
    before = tree(data)
    r = run("optimize", data, "-o", tmp_path / "run", "--iterations", "5", "--cache", data / "cache", "--quiet")
    assert_one_line_error(r, "--cache", "lies in the dataset folder")
    assert tree(data) == before and not (data / "cache").exists()
    r = run("points", data, "-o", tmp_path / "p.ply", "--cache", data / "cache")
    assert_one_line_error(r, "--cache", "lies in the dataset folder")
    assert tree(data) == before and not (tmp_path / "p.ply").exists()


def test_overwrite_leaves_a_run_folder_in_use_alone(tmp_path):
    """--overwrite takes each run folder's lock before it removes anything there: an optimize still running in one
    (here: its lock held) gets its files kept, and the sweep stops in one line before removing anything."""
    from mi_gaussians.run_folder import RunLock

    spec = write_spec(tmp_path / "s.toml", SPEC.format(a=DATA / "tiny_blender", b=DATA / "tiny_colmap"))
    runs = read_spec(spec).runs
    out = tmp_path / "out"
    write_spec(out / "spec.toml", spec.read_text())                       # an earlier sweep's folder
    (out / "cache").mkdir()
    for r in runs:
        (out / "runs" / r.name / "checkpoints").mkdir(parents=True)
        (out / "runs" / r.name / "checkpoints" / "ckpt.npz").write_bytes(b"a run's checkpoint")
    before = tree(out)
    lock = RunLock(out / "runs" / runs[-1].name).acquire()                # a live optimize there
    try:
        assert_one_line_error(run("sweep", spec, "-o", out, "--overwrite"), str(out / "runs" / runs[-1].name),
                              "another mi-gs process", f"PID {os.getpid()}")
    finally:
        lock.release()
    assert {k: v for k, v in tree(out).items() if not k.endswith(".lock")} == before


# -------------------------------------------------------------------------------------- bounded waits: no hangs
def test_an_address_where_nothing_listens_is_one_line_within_the_bound(tmp_path):
    """Ray retried such an address for 10 minutes and more, printing only its own warnings."""
    import socket

    connect_s = 5

    with socket.socket() as s:                  # a port that nothing listens on (bound, then closed)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    spec = write_spec(tmp_path / "s.toml", f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 5\n')
    t0 = time.monotonic()
    r = run("sweep", spec, "-o", tmp_path / "out", "--address", f"127.0.0.1:{port}", "--connect-timeout", connect_s)
    assert time.monotonic() - t0 < connect_s + 60
    assert_one_line_error(r, f"--address 127.0.0.1:{port}: nothing answers there")
    assert not (tmp_path / "out").exists()
    for bad in ("nowhere", "host:port", "[::1]:99999"):
        assert_one_line_error(run("sweep", spec, "-o", tmp_path / "out", "--address", bad), "expected HOST:PORT")
    # mi-gs optimize --workers N --address joins a cluster the same way
    scene = ROOT / "scenes" / "objects.xml"
    t0 = time.monotonic()
    r = run("optimize", scene, "-o", tmp_path / "run", "--workers", 2, "--address", f"127.0.0.1:{port}")
    assert time.monotonic() - t0 < 90
    assert_one_line_error(r, f"--address 127.0.0.1:{port}: nothing answers there")
    assert not (tmp_path / "run").exists()
    for bad in ("0", "-1", "inf", "nan", "soon"):
        assert_one_line_error(run("sweep", spec, "-o", tmp_path / "out", "--stop-timeout", bad), "--stop-timeout")
    from mi_gaussians.cluster.ray_cluster import Waits

    assert Waits().connect == 30.0
    with pytest.raises(ValueError, match="waits.stop: expected a positive number of seconds"):
        Waits(stop=0)


def test_resources_no_node_has_are_refused_not_waited_for(ray_cluster, tmp_path):
    """Ray keeps a task that no node can hold waiting for ever (the sweep hung at 0/1): refused in one line."""
    for resources, words in (("cpus = 64", "resources.cpus: 64 per run, but the largest node has 2"),
                             ("gpus = 1", "resources.gpus: 1 per run, but no node of the cluster has a GPU")):
        spec = write_spec(tmp_path / "s.toml", f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 5\n'
                                               f"[resources]\n{resources}\n")
        t0 = time.monotonic()
        r = run("sweep", spec, "-o", tmp_path / "out", "--address", ray_cluster)
        assert time.monotonic() - t0 < 120
        assert_one_line_error(r, str(spec), words)
        assert not (tmp_path / "out" / "runs").exists()


def test_a_lost_run_says_what_died_once():
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install '.[test]' brings it)")
    from mi_gaussians.cluster.sweep import lost_line

    node = lost_line(ray, ray.exceptions.LocalRayletDiedError(), 3)
    assert node.startswith("the node running it died (LocalRayletDiedError); run the same command again")
    assert "4 times" not in node
    assert lost_line(ray, ray.exceptions.NodeDiedError("gone"), 3).startswith("the node running it died")
    worker = lost_line(ray, ray.exceptions.WorkerCrashedError(), 3)
    assert worker.startswith("its worker process died 4 times (WorkerCrashedError); run the same command again")


def test_resources_must_fit_on_one_node():
    """CPUs on one node and a GPU on another do not make a node that holds the run."""
    from types import SimpleNamespace

    from mi_gaussians.cluster.ray_cluster import check_resources

    ray = SimpleNamespace(nodes=lambda: [{"Alive": True, "Resources": {"CPU": 64.0}},
                                         {"Alive": True, "Resources": {"CPU": 4.0, "GPU": 1.0}},
                                         {"Alive": False, "Resources": {"CPU": 128.0, "GPU": 8.0}}])
    check_resources(ray, 4, 1, "s.toml: resources")
    check_resources(ray, 64, 0, "s.toml: resources")
    with pytest.raises(ValueError, match=r"8 CPUs and 1 GPUs per run, but no node has both \(2 nodes"):
        check_resources(ray, 8, 1, "s.toml: resources")
    with pytest.raises(ValueError, match=r"resources.gpus: 2 per run, but the largest node has 1"):
        check_resources(ray, 1, 2, "s.toml: resources")


RAYLET_DIED = ("\x1b[33m(raylet)\x1b[0m Raylet is terminated. Termination is unexpected. Possible reasons include: (1) "
               "SIGKILL by the user or system OOM killer. Last 20 lines of the Raylet logs:\n"
               "    [state-dump] \tNodeManager.GCTaskFailureReason - 1 total (1 active), Execution time: mean = 0.00ms\n"
               "    [state-dump] \tray::rpc::NodeInfoGcsService.grpc_client.RegisterNode - 1 total (0 active)\n")


TASK_RETRIED = ("Task train_task failed. There are 3 retries remaining, so the task will be retried. Error: Task failed "
                "because the node it was running on is dead or unavailable. Node IP: 192.0.2.2, node ID: 2d48bc08.")


MARKED_DEAD = ("The node with node id: 07d1c9cc and address: 192.0.2.2 and node name: 192.0.2.2 has been marked dead "
               "because the detector has missed too many heartbeats from it.")


def test_what_the_cluster_pushes_to_the_driver_is_one_line_on_stderr(capfd):
    """A raylet's death reaches every driver as a message that Ray's own thread prints to stdout, with colour codes
    and 20 lines of the raylet's state dumps (seen with a node killed under a real two-node sweep; `log_to_driver`
    does not turn it off): while connected, it is one line on stderr, said once, and stdout stays the results'."""
    import ray
    import ray._private.worker as ray_worker

    from mi_gaussians.cluster.ray_cluster import NODE_DIED, cluster_messages_to_stderr

    # (the hook point: Ray's listener calls the module's printer by name, for every message)
    assert "print_to_stdstream(" in __import__("inspect").getsource(ray_worker.listen_error_messages)
    message = {"lines": [RAYLET_DIED], "pid": "raylet", "is_err": False}
    with cluster_messages_to_stderr(ray):
        ray_worker.print_to_stdstream(message, ignore_prefix=False)
        ray_worker.print_to_stdstream(dict(message), ignore_prefix=False)
    out, err = capfd.readouterr()
    assert out == ""
    assert err.splitlines() == [f"ray: {NODE_DIED}"]
    with cluster_messages_to_stderr(ray):                           # (Ray's second message of the same death)
        ray_worker.print_to_stdstream({"lines": [TASK_RETRIED], "pid": "raylet", "is_err": False}, ignore_prefix=False)
        ray_worker.print_to_stdstream({"lines": [MARKED_DEAD], "pid": "raylet", "is_err": False}, ignore_prefix=False)
        ray_worker.print_to_stdstream({"lines": [RAYLET_DIED], "pid": "raylet", "is_err": False}, ignore_prefix=False)
        ray_worker.print_to_stdstream({"lines": ["\x1b[31mSomething else.\x1b[0m\nmore"], "pid": "raylet",
                                       "is_err": False}, ignore_prefix=False)
    out, err = capfd.readouterr()
    assert out == "" and err.splitlines() == [f"ray: {NODE_DIED}", "ray: Something else."]
    with cluster_messages_to_stderr(ray, quiet_seconds=0.0):        # (a second death, later: said again)
        for _ in range(2):
            ray_worker.print_to_stdstream(message, ignore_prefix=False)
    assert capfd.readouterr().err.splitlines() == [f"ray: {NODE_DIED}"] * 2
    ray_worker.print_to_stdstream(message, ignore_prefix=False)      # (afterwards: Ray's own printer again)
    assert "[state-dump]" in capfd.readouterr().out


def test_a_cluster_with_token_authentication_is_named_in_the_error(monkeypatch):
    """`ray start` turns token authentication on (Ray 2.60 does); a driver without RAY_AUTH_MODE=token is refused after
    Ray's retries: the one line says what to set."""
    import ray

    from mi_gaussians.cluster import ray_cluster

    def refused(*args, **kwargs):
        raise ConnectionError("Failed to connect to Ray cluster at 10.0.0.1:6379")

    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    monkeypatch.setattr(ray_cluster, "check_reachable", lambda address, seconds: None)
    monkeypatch.setattr(ray, "init", refused)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    with pytest.raises(ValueError) as e:
        with ray_cluster.connected("10.0.0.1:6379"):
            pass
    assert "\n" not in str(e.value) and "RAY_AUTH_MODE=token" in str(e.value)
    assert str(e.value).startswith("--address 10.0.0.1:6379: cannot join the Ray cluster there")


def _raylet_pids(session_root: Path) -> dict[str, int]:
    """socket name -> pid of every raylet whose sockets lie under ``session_root`` (``raylet``: the head's)."""
    found = {}
    for proc in Path("/proc").iterdir():
        try:
            args = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        for a in args:
            a = a.decode(errors="replace")
            if a.startswith("--raylet_socket_name=") and str(session_root) in a:
                found[Path(a.split("=", 1)[1]).name] = int(proc.name)
    return found


@pytest.mark.slow
def test_a_dead_node_is_one_line_and_its_run_resumes_on_another(tmp_path):
    """A real two-node cluster (`ray start`: a head and a second node of 1 CPU each, one run on each); once both runs
    have checkpointed, the second node's raylet is killed (SIGKILL). The sweep ends by itself, both runs done (the
    lost one resumed from its checkpoint on the head), stdout holds the results only (no colour codes, no state
    dumps), and stderr says once what Ray said."""
    import socket as socket_module

    ray_exe = str(Path(sys.executable).parent / "ray")
    with socket_module.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    temp = Path(tempfile.mkdtemp(prefix="rk", dir="/tmp"))      # (short: Ray's socket paths are limited)
    env = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
    spec = write_spec(tmp_path / "spec.toml", f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 1500\n'
                                              'seeds = [0, 1]\n[set]\n"data.random_points" = 2000\neval_every = 0\n'
                                              'checkpoint_every = 100\n[resources]\ncpus = 1\n')
    out = tmp_path / "out"
    subprocess.run([ray_exe, "start", "--head", f"--port={port}", "--num-cpus=1", "--include-dashboard=false",
                    f"--temp-dir={temp}", "--node-ip-address=127.0.0.1"], env=env, check=True, capture_output=True,
                   timeout=120)
    try:
        subprocess.run([ray_exe, "start", f"--address=127.0.0.1:{port}", "--num-cpus=1",
                        "--node-ip-address=127.0.0.1"], env=env, check=True, capture_output=True, timeout=120)
        sweep = subprocess.Popen([EXE, "sweep", str(spec), "-o", str(out), "--address", f"127.0.0.1:{port}"],
                                 env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 240
            while min(checkpoint_step(out / "runs" / f"tiny_blender-s{k}") for k in (0, 1)) < 100:
                assert time.monotonic() < deadline and sweep.poll() is None, "the runs did not checkpoint in time"
                time.sleep(0.05)
            raylets = _raylet_pids(temp)
            assert set(raylets) == {"raylet", "raylet.1"}, raylets
            os.kill(raylets["raylet.1"], signal.SIGKILL)
            stdout, stderr = sweep.communicate(timeout=300)
        finally:
            if sweep.poll() is None:
                sweep.kill()
    finally:
        subprocess.run([ray_exe, "stop", "--force"], env=env, capture_output=True, timeout=120)
    assert sweep.returncode == 0, stderr[-3000:]
    assert [r["status"] for r in rows(out)] == ["done", "done"], stderr[-3000:]
    assert sum(r["resumed_at"] != "" for r in rows(out)) == 1
    assert "\x1b[" not in stdout and "[state-dump]" not in stdout and "Raylet" not in stdout, stdout
    assert stdout.splitlines()[-1].startswith("2 of 2 runs done")
    said = [line for line in stderr.replace("\r", "\n").splitlines() if "ray: " in line]
    from mi_gaussians.cluster.ray_cluster import NODE_DIED

    assert said == [f"ray: {NODE_DIED}"], stderr[-3000:]
