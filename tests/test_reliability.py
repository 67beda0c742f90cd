"""Misuse of ``mi-gs`` that used to lose a run, mix two runs or print a traceback (issue #13): each gets one line
``mi-gs: error: ...`` with exit status 2, before anything in the output folder is touched."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from mi_gaussians import run_folder
from mi_gaussians.run_folder import RunLock

from test_cli import assert_one_line_error, run

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
SCENES = ROOT / "scenes"

TRAIN = ("--iterations", 6, "--checkpoint-every", 3, "--eval-every", 0, "--quiet")


def snapshot(folder: Path) -> dict:
    """Every file under ``folder`` (except the lock file) and its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != run_folder.LOCK}


def corrupt(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 3])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished 6-iteration run on a copy of tiny_blender: (dataset folder, run folder)."""
    base = tmp_path_factory.mktemp("trained")
    data = base / "data"
    shutil.copytree(DATA / "tiny_blender", data)
    out = base / "run"
    res = run("optimize", data, "-o", out, *TRAIN)
    assert res.returncode == 0, res.stderr
    return data, out


@pytest.fixture
def copy_of(trained, tmp_path):
    """A private copy of the trained run and its dataset: (dataset folder, run folder)."""
    data, out = tmp_path / "data", tmp_path / "run"
    shutil.copytree(trained[0], data)
    shutil.copytree(trained[1], out)
    # the recorded dataset is the module's copy: point the record at this one
    cfg = json.loads((out / "config.json").read_text())
    cfg["dataset"] = str(data.resolve())
    (out / "config.json").write_text(json.dumps(cfg))
    return data, out


# ---------------------------------------------------------------------------------------------------- 1. validate first
def test_overwrite_with_an_unreadable_image_keeps_the_earlier_run(copy_of):
    data, out = copy_of
    before = snapshot(out)
    corrupt(data / "test" / "r_0.png")              # a test view: read only at evaluation time until now
    assert_one_line_error(run("optimize", data, "-o", out, "--overwrite", *TRAIN), "r_0.png", "not a readable image")
    assert snapshot(out) == before


def test_info_lists_unreadable_images(tmp_path):
    data = tmp_path / "data"
    shutil.copytree(DATA / "tiny_blender", data)
    corrupt(data / "train" / "r_1.png")
    res = run("info", data)
    assert_one_line_error(res, "1 of 3 images cannot be read")
    info = json.loads(res.stdout)
    assert info["images_checked"] == 3
    assert len(info["unreadable_images"]) == 1 and "r_1.png" in info["unreadable_images"][0]
    assert json.loads(run("info", DATA / "tiny_blender").stdout)["unreadable_images"] == []


# ---------------------------------------------------------------------------------------------------- 2. one run per folder
def test_a_folder_in_use_is_refused_and_left_alone(copy_of):
    data, out = copy_of
    before = snapshot(out)
    with RunLock(out):                               # another live process holds it (a flock is per process)
        assert_one_line_error(run("optimize", data, "-o", out, "--overwrite", *TRAIN),
                              "another mi-gs process", f"PID {os.getpid()}")
        assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--quiet"), "another mi-gs process")
        assert_one_line_error(run("eval", out), "another mi-gs process")
    assert snapshot(out) == before


def test_two_runs_started_together_do_not_mix(tmp_path):
    """Two real processes on one folder: one trains, the other is refused with the first one's PID."""
    exe = Path(sys.executable).parent / "mi-gs"
    out = tmp_path / "run"
    # (so many iterations that the first run is still training when the second one asks; killed afterwards)
    first = subprocess.Popen([str(exe), "optimize", str(DATA / "tiny_blender"), "-o", str(out), "--iterations",
                              "1000000", "--checkpoint-every", "50", "--quiet"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not ((out / run_folder.LOCK).exists()
                                              and (out / run_folder.LOCK).read_text().strip()):
            time.sleep(0.05)
        assert (out / run_folder.LOCK).read_text().strip() == str(first.pid)
        second = run("optimize", DATA / "tiny_ngp", "-o", out, "--iterations", 5, "--quiet")
        assert first.poll() is None, "the first run ended early"
        assert_one_line_error(second, "another mi-gs process", f"PID {first.pid}")
        deadline = time.time() + 300
        while time.time() < deadline and not (out / "config.json").exists():
            time.sleep(0.1)
    finally:
        first.kill()
        first.wait(timeout=60)
    assert json.loads((out / "config.json").read_text())["dataset"] == str((DATA / "tiny_blender").resolve())


def test_a_lock_left_by_a_dead_run_is_taken_over(copy_of):
    data, out = copy_of
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (out / run_folder.LOCK).write_text(dead.stdout)   # a PID that is gone, and no flock held
    res = run("optimize", data, "-o", out, "--resume", "--iterations", 8, "--quiet")
    assert res.returncode == 0, res.stderr


def test_a_refused_new_run_leaves_no_folder(tmp_path):
    out = tmp_path / "new"
    assert_one_line_error(run("optimize", DATA / "tiny_blender", "-o", out, "-r", 100, "--quiet"), "at least 16")
    assert not out.exists()


# ---------------------------------------------------------------------------------------------------- 3. resume
def test_resume_refuses_another_dataset_folder(copy_of, tmp_path):
    data, out = copy_of
    before = snapshot(out)
    other = tmp_path / "other"
    shutil.copytree(data, other)
    assert_one_line_error(run("optimize", other, "-o", out, "--resume", "--quiet"), "was trained on", str(other))
    assert snapshot(out) == before


def test_resume_accepts_a_fingerprint_of_an_earlier_version_with_a_warning(copy_of):
    data, out = copy_of
    cfg = json.loads((out / "config.json").read_text())
    cfg["dataset_fingerprint"] = "0" * 64          # the unversioned digest of the first fingerprint
    (out / "config.json").write_text(json.dumps(cfg))
    res = run("optimize", data, "-o", out, "--resume", "--iterations", 7, "--quiet")
    assert res.returncode == 0, res.stderr
    assert "fingerprint of an earlier mi-gs" in res.stderr
    from mi_gaussians.data.dataset import FINGERPRINT_VERSION

    assert json.loads((out / "config.json").read_text())["dataset_fingerprint"].startswith(FINGERPRINT_VERSION + ":")


def test_resume_refuses_a_changed_dataset(copy_of):
    data, out = copy_of
    before = snapshot(out)
    shutil.copy(data / "train" / "r_1.png", data / "train" / "r_0.png")     # same folder, other content
    assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--quiet"), "dataset changed")
    assert snapshot(out) == before


def test_resume_refuses_options_that_change_the_run(copy_of):
    data, out = copy_of
    before = snapshot(out)
    assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--sh-degree", 1, "--quiet"),
                          "--sh-degree", "optim.sh_degree")
    assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--background", 1, "--quiet"),
                          "--background", "data.background")
    assert snapshot(out) == before
    # an option given again with the run's own value is fine; a parser default given explicitly is an option given
    res = run("optimize", data, "-o", out, "--resume", "--seed", 0, "--quiet")
    assert res.returncode == 0, res.stderr
    cfg = json.loads((out / "config.json").read_text())
    cfg["train"]["optim"]["sh_degree"] = 1
    (out / "config.json").write_text(json.dumps(cfg))
    assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--sh-degree", 3, "--quiet"),
                          "--sh-degree gives optim.sh_degree = 3, the run has 1")


def test_resume_extends_iterations_and_refuses_going_back(copy_of):
    data, out = copy_of
    assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--iterations", 4, "--quiet"),
                          "already at iteration 6")
    res = run("optimize", data, "-o", out, "--resume", "--iterations", 9, "--quiet")
    assert res.returncode == 0, res.stderr
    history = json.loads((out / "history.json").read_text())
    assert history["iteration"][-1] == 9
    cfg = json.loads((out / "config.json").read_text())["train"]["optim"]
    assert cfg["iterations"] == 9 and cfg["position_lr_max_steps"] == 6      # the run's schedule is kept


def test_stale_temporary_files_are_removed(copy_of):
    data, out = copy_of
    stale = [out / "checkpoints" / ".ckpt.npz.k1l2m3_9.tmp.npz", out / ".metrics.json.x9y8ab_c.tmp.json",
             out / "renders" / ".r_0.png.q2w3e4r5.tmp.png"]
    foreign = [out / ".env.tmpl", out / "notes.tmp", out / "checkpoints" / ".other.tmp"]   # not ours: kept
    for p in stale + foreign:
        p.write_bytes(b"partial")
    res = run("optimize", data, "-o", out, "--resume", "--iterations", 7, "--quiet")
    assert res.returncode == 0, res.stderr
    assert not any(p.exists() for p in stale)
    assert all(p.exists() for p in foreign)


# ---------------------------------------------------------------------------------------------------- 4. tracebacks
def test_output_path_of_the_wrong_kind(tmp_path):
    a_file = tmp_path / "file.txt"
    a_file.write_text("keep me")
    assert_one_line_error(run("optimize", DATA / "tiny_blender", "-o", a_file, "--quiet"), "is a file, not a folder")
    assert a_file.read_text() == "keep me"
    folder = tmp_path / "x.png"
    folder.mkdir()
    assert_one_line_error(run("render", SCENES / "tiny_gaussians.ply", "--camera",
                              SCENES / "tiny_gaussians_camera.json", "-o", folder), "is a folder, not a file")
    assert_one_line_error(run("render", SCENES / "tiny_gaussians.ply", "--camera",
                              SCENES / "tiny_gaussians_camera.json", "-o", a_file / "x.png"), "is a file, not a folder")


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_output_folder(tmp_path):
    locked = tmp_path / "ro"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        assert_one_line_error(run("optimize", DATA / "tiny_blender", "-o", locked / "run", "--quiet"), "not writable")
    finally:
        locked.chmod(0o755)


def test_variants_mi_gs_cannot_use():
    assert_one_line_error(run("--variant", "scalar_rgb", "info", SCENES / "tiny_gaussians.ply"), "scalar_rgb",
                          "llvm_ad_rgb")
    assert_one_line_error(run("--variant", "nosuch", "info", SCENES / "tiny_gaussians.ply"), "not a Mitsuba variant")


def test_cuda_variant_without_a_gpu():
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a CUDA device")
    assert_one_line_error(run("--variant", "cuda_ad_rgb", "info", SCENES / "tiny_gaussians.ply"), "no CUDA device")


def test_variant_after_the_subcommand():
    res = run("info", SCENES / "tiny_gaussians.ply", "--variant", "llvm_ad_rgb")
    assert res.returncode == 0, res.stderr
    assert_one_line_error(run("info", SCENES / "tiny_gaussians.ply", "--variant", "scalar_rgb"), "scalar_rgb")


def test_resume_with_a_config_without_training_settings(copy_of):
    data, out = copy_of
    cfg = json.loads((out / "config.json").read_text())
    del cfg["train"]
    (out / "config.json").write_text(json.dumps(cfg))
    assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--quiet"), "config.json", "training settings")
    (out / "config.json").write_text("[1, 2]")
    assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--quiet"), "config.json")


def test_broken_pipe_is_one_line():
    exe = Path(sys.executable).parent / "mi-gs"
    proc = subprocess.Popen([str(exe), "info", str(DATA / "tiny_blender")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=tempfile.gettempdir())
    proc.stdout.close()                              # the reader goes away before anything is written
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("mi-gs: error: ") and "broken pipe" in lines[0], err


# ---------------------------------------------------------------------------------------------------- 5. Mitsuba's errors
def test_mitsuba_errors_keep_their_cause(tmp_path):
    assert_one_line_error(run("info", SCENES / "objects.xml", "-D", "nosuch=1"), "unused parameters", "nosuch=1")
    scene = tmp_path / "inc.xml"
    scene.write_text('<scene version="3.0.0"><include filename="nothere.xml"/></scene>')
    assert_one_line_error(run("info", scene), "nothere.xml", "not found", "line 1")


# ---------------------------------------------------------------------------------------------------- 6. nonsense
@pytest.mark.parametrize("args, needle", [
    (("--iterations", "-5"), "--iterations: expected a positive integer"),
    (("--iterations", "0"), "--iterations: expected a positive integer"),
    (("--background", "nan"), "--background: expected a finite number"),
    (("--background", "1", "inf", "0"), "--background: expected a finite number"),
    (("--sh-degree", "4"), "--sh-degree: expected an SH degree"),
    (("--checkpoint-every", "0"), "--checkpoint-every"),
    (("-r", "0"), "--resolution: expected a positive integer"),
    (("-r", "100"), "at least 16 per side"),
])
def test_nonsense_options_are_refused(tmp_path, args, needle):
    out = tmp_path / "run"
    assert_one_line_error(run("optimize", DATA / "tiny_blender", "-o", out, "--quiet", *args), needle)
    assert not out.exists()


def test_resolution_with_a_camera_json_is_refused(tmp_path):
    assert_one_line_error(run("render", SCENES / "tiny_gaussians.ply", "--camera", SCENES / "tiny_gaussians_camera.json",
                              "-r", 2, "-o", tmp_path / "a.png"), "--resolution applies to --dataset only")
    assert not (tmp_path / "a.png").exists()


def test_a_hand_edited_config_json_is_one_line_naming_the_key(copy_of):
    """Wrong types and values in config.json are refused by every command that reads it, naming the file and the
    key (a string "300" is not read as a number, "false" not as true, a checkpoint period of 0 not divided by)."""
    data, out = copy_of
    good = json.loads((out / "config.json").read_text())
    for section, key, value in (("optim", "iterations", "300"), ("raster", "antialiased", "false"),
                                (None, "seed", "abc"), (None, "checkpoint_every", 0)):
        cfg = json.loads(json.dumps(good))
        (cfg["train"][section] if section else cfg["train"])[key] = value
        (out / "config.json").write_text(json.dumps(cfg))
        name = f"train.{section}.{key}" if section else f"train.{key}"
        before = snapshot(out)
        assert_one_line_error(run("optimize", data, "-o", out, "--resume", "--quiet"), "config.json", name)
        assert_one_line_error(run("eval", out), "config.json", name)
        assert snapshot(out) == before
