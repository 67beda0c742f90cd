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
    again = run("sweep", spec, "-o", out, "--address", ray_cluster, "--quiet")
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


def test_distributed_references_equal_single_process_ones(ray_cluster, tmp_path):
    """``mi-gs optimize scene.xml --workers 2``: the references rendered by two Ray workers (each loading the scene
    once, with its -D values) are the files one process renders, bit for bit (images and depths)."""
    from mi_gaussians.config import SceneConfig
    from mi_gaussians.data.scene_dataset import load_scene_dataset
    from test_mitsuba_scene import write_scene

    scene = write_scene(tmp_path / "scene.xml", w=24, h=24, spp=4, sky="$sky")
    scene.write_text(scene.read_text().replace("<sensor", '<default name="sky" value="0.2"/><sensor', 1))
    r = run("optimize", scene, "-o", tmp_path / "run", "--workers", "2", "--address", ray_cluster, "--iterations", 5,
            "--views", 5, "--test-views", 2, "-D", "sky=0.6", "--init", "random", "--init-points", 200, "--quiet")
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
    ('datasets = ["{a}"]\n[resources]\ncpus = 0', "resources.cpus: expected a number > 0"),
    ('datasets = ["{a}"]\n[resources]\nram = 2', "resources.ram: not a resource"),
    ('datasets = ["{a}"', "not valid TOML"),
])
def test_bad_specs_are_one_line_naming_the_key(tmp_path, text, words):
    spec = write_spec(tmp_path / "spec.toml", text.replace("{a}", str(DATA / "tiny_blender")))
    with pytest.raises(ValueError) as e:
        read_spec(spec)
    assert words in str(e.value) and str(spec) in str(e.value) and "\n" not in str(e.value), str(e.value)


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
