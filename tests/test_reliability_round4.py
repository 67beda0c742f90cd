"""Reliability, fourth round (issue 54): every port, host and image size is checked before anything starts, a sweep's
grid holds scalars, a scene without a length scale is refused, nothing is silent for long, a setting with no effect
says so, and the "poor" cases of the probe each give a clear line. One test (or more) per case, through the installed
``mi-gs`` (the command line's behaviour is what the user sees); each failed before its fix.

(The non-finite guard over every trained quantity and the identity of a checkpoint are tested where they live, with
the trainer.)"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from mi_gaussians import run_folder
from test_cli import assert_one_line_error

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
SCENES = ROOT / "scenes"
SHARED = ROOT.parent / "shared" / "data"
EXE = str(Path(sys.executable).parent / "mi-gs")
TRAIN = ("--iterations", 6, "--checkpoint-every", 3, "--eval-every", 0, "--random-points", 300)


def run(*args, cwd=None, env=None, timeout=600):
    """``mi-gs args`` (the installed console script) in ``cwd`` (default: the temporary folder) with ``env`` added."""
    return subprocess.run([EXE, *map(str, args)], capture_output=True, text=True, timeout=timeout,
                          cwd=cwd or tempfile.gettempdir(), env={**os.environ, **(env or {})})


def notes(res) -> list[str]:
    return [ln for ln in res.stderr.splitlines() if ln.startswith("note: ")]


def warnings(res) -> list[str]:
    return [ln for ln in res.stderr.splitlines() if ln.startswith("mi-gs: warning: ")]


@pytest.fixture(scope="module")
def blender(tmp_path_factory) -> Path:
    """tiny_blender with its images four times as large (96x64: room for -r 2)."""
    from PIL import Image

    d = tmp_path_factory.mktemp("r4") / "blender"
    shutil.copytree(DATA / "tiny_blender", d)
    for png in d.rglob("*.png"):
        with Image.open(png) as im:
            im.resize((im.width * 4, im.height * 4), Image.Resampling.NEAREST).save(png)
    for f in d.glob("transforms_*.json"):
        t = json.loads(f.read_text())
        t.update(fl_x=t["fl_x"] * 4, fl_y=t["fl_y"] * 4, cx=(t["cx"] + 0.5) * 4 - 0.5, cy=(t["cy"] + 0.5) * 4 - 0.5,
                 w=t["w"] * 4, h=t["h"] * 4)
        f.write_text(json.dumps(t))
    return d


@pytest.fixture(scope="module")
def white_run(blender, tmp_path_factory) -> Path:
    """A finished run on tiny_blender, trained on white at -r 2."""
    out = tmp_path_factory.mktemp("r4") / "white"
    r = run("optimize", blender, "-o", out, *TRAIN, "--quiet", "--white-background", "-r", 2)
    assert r.returncode == 0, r.stderr
    return out


@pytest.fixture(scope="module")
def colmap(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("r4") / "tiny_colmap"
    shutil.copytree(DATA / "tiny_colmap", d)
    return d


@pytest.fixture(scope="module")
def refined_run(colmap, tmp_path_factory):
    """A finished --pose-opt --exposure run on tiny_colmap with no test views (--test-every 0): (the run's folder,
    what optimize printed)."""
    out = tmp_path_factory.mktemp("r4") / "refined"
    r = run("optimize", colmap, "-o", out, *TRAIN, "--pose-opt", "--exposure", "--test-every", 0)
    assert r.returncode == 0, r.stderr
    return out, r


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------- ports, hosts, image sizes
def test_a_port_out_of_range_is_one_line_before_anything_starts(white_run, tmp_path):
    t = time.perf_counter()
    assert_one_line_error(run("view", white_run, "--port", 70000), "--port", "1 to 65535", "70000")
    assert_one_line_error(run("view", white_run, "--host", "no-such-host.invalid"), "--host no-such-host.invalid")
    assert_one_line_error(run("view", white_run, "--max-size", 100000), "--max-size", "128 to 4096")
    assert time.perf_counter() - t < 60                       # (was: a traceback, then a hang until killed)
    # optimize --view: checked before the dataset is read or a folder made
    out = tmp_path / "never"
    assert_one_line_error(run("optimize", DATA / "tiny_blender", "-o", out, *TRAIN, "--view", "--port", 70000),
                          "70000")
    assert_one_line_error(run("optimize", DATA / "tiny_blender", "-o", out, *TRAIN, "--view", "--host",
                              "no-such-host.invalid"), "no-such-host.invalid")
    assert not out.exists()


def test_an_image_nobody_has_memory_for_is_refused_with_the_estimate(white_run, tmp_path):
    cam = json.loads((SCENES / "tiny_gaussians_camera.json").read_text())
    cam.update(width=100000, height=75000)
    (tmp_path / "cam.json").write_text(json.dumps(cam))
    t = time.perf_counter()
    r = run("render", white_run / "point_cloud.ply", "--camera", tmp_path / "cam.json", "-o", tmp_path / "big.png")
    assert_one_line_error(r, "cam.json", "100,000x75,000", "GiB", "more than")
    assert time.perf_counter() - t < 60 and not (tmp_path / "big.png").exists()   # (was: 8 GB in 35 s, growing)
    # a scene's film size (-r W H), before any reference is rendered
    out = tmp_path / "run"
    r = run("optimize", SCENES / "objects.xml", "-o", out, "-r", 100000, 75000, "--quiet")
    assert_one_line_error(r, "objects.xml", "100,000x75,000", "GiB", "-r W [H]")
    assert not out.exists()


# ---------------------------------------------------------------------------------------------------- sweeps
def test_a_sweep_grid_of_lists_is_refused_at_the_spec_check(tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text(f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 6\n[grid]\n'
                    'strategy = [["default"], ["mcmc"]]\n')
    r = run("sweep", spec, "-o", tmp_path / "out")
    assert_one_line_error(r, "spec.toml: grid.strategy", "one number, string or true/false", "['default']")
    assert not (tmp_path / "out").exists()


def test_the_results_writer_takes_every_value_the_spec_check_accepts(tmp_path):
    from mi_gaussians.cluster import results
    from mi_gaussians.cluster.sweep_spec import read_spec

    spec = tmp_path / "spec.toml"
    spec.write_text(f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 6\n[grid]\nstrategy = ["default", "mcmc"]\n'
                    '"optim.random_background" = [true, false]\n"optim.lambda_dssim" = [0.2, 1]\n'
                    '"data.background" = ["0,0,0", "1,1,1"]\n')
    s = read_spec(spec)
    rows = [results.row(p, "done", {"mean": {"psnr": 20.0 + i}, "gaussians": 300}) for i, p in enumerate(s.runs)]
    results.write(tmp_path, rows, s.grid_keys, "sweep")
    assert len(results.means(rows, s.grid_keys)) == 16
    assert "| default | True | 0.2 | 0,0,0 | 1 of 1 |" in (tmp_path / "results.md").read_text()
    # (rows of another writer, with a list in a grid column, group by its text: the table is still written)
    odd = [{**rows[0], "strategy": ["default"]}, {**rows[1], "strategy": ["default"]}]
    results.write(tmp_path, odd, s.grid_keys, "sweep")


def test_a_sweep_says_what_in_its_spec_has_no_effect(tmp_path):
    from mi_gaussians.cluster.sweep_spec import read_spec

    spec = tmp_path / "spec.toml"
    spec.write_text(f'datasets = ["{DATA / "tiny_blender"}"]\niterations = 6\n[set]\n"optim.pose_opt_lr" = 0.001\n'
                    '[grid]\n"densify.grad_threshold" = [0.0002]\n')
    said = read_spec(spec).notes
    assert any("grid.densify.grad_threshold has one value (0.0002)" in n for n in said), said
    assert any("set.optim.pose_opt_lr has no effect" in n and "--pose-opt" in n for n in said), said


# ------------------------------------------------------------------------------------- scale, convert, -o ''
def _one_camera_seeing_nothing(tmp_path: Path, keep: int) -> Path:
    """tiny_colmap with its first ``keep`` images, and its points moved where no camera sees them (behind the first
    camera, or out of every image)."""
    from mi_gaussians.data.dataset import load_dataset

    d = tmp_path / f"unseen{keep}"
    shutil.copytree(DATA / "tiny_colmap", d)
    images = (d / "sparse" / "0" / "images.txt").read_text().splitlines()
    head, body = [ln for ln in images if ln.startswith("#")], [ln for ln in images if not ln.startswith("#")]
    (d / "sparse" / "0" / "images.txt").write_text("\n".join(head + body[:2 * keep]) + "\n")
    cams = [v.camera for v in load_dataset(d, test_every=0).train]
    rng = np.random.default_rng(0)
    behind = cams[0].center - 3.0 * cams[0].world_to_camera[2, :3] + 0.1 * rng.standard_normal((50, 3))
    seen = np.zeros(len(behind), bool)
    for c in cams:
        seen |= c.sees(*c.project(behind))
    points = behind[~seen][:6]
    assert len(points) == 6
    lines = [f"{i + 1} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} 128 128 128 0 1 {i}" for i, p in enumerate(points)]
    (d / "sparse" / "0" / "points3D.txt").write_text("\n".join(lines) + "\n")
    return d


def test_a_scene_without_a_length_scale_is_refused(tmp_path):
    data = _one_camera_seeing_nothing(tmp_path, keep=1)
    out = tmp_path / "run"
    r = run("optimize", data, "-o", out, *TRAIN, "--quiet", "--test-every", 0)
    assert_one_line_error(r, str(data), "no length scale", "1 training camera, so no spread",
                          "--init frustum")
    assert not out.exists()                     # (was: exit 0, "extent": 0.0, Gaussians that never moved)


def test_points_no_camera_sees_fall_back_to_the_cameras_spread_with_a_note(tmp_path):
    data = _one_camera_seeing_nothing(tmp_path, keep=3)
    r = run("optimize", data, "-o", tmp_path / "run", *TRAIN, "--quiet", "--test-every", 0)
    assert r.returncode == 0, r.stderr
    said = [n for n in notes(r) if "falls back to the cameras' spread" in n]
    assert len(said) == 1 and "none of the 6 initial points" in said[0], r.stderr
    from mi_gaussians.data.dataset import load_dataset

    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["extent"] == pytest.approx(load_dataset(data, test_every=0).extent, rel=1e-4)


def _convert_input(tmp_path: Path, real: int) -> Path:
    """``real`` neighbouring turntable views and six images of noise."""
    from PIL import Image

    d = tmp_path / f"photos{real}"
    d.mkdir()
    for p in sorted((SCENES / "turntable_images").iterdir())[:real]:
        shutil.copy(p, d / p.name)
    rng = np.random.default_rng(0)
    for i in range(6):
        Image.fromarray((rng.random((200, 200, 3)) * 255).astype(np.uint8)).save(d / f"noise_{i}.png")
    return d


def test_convert_reports_how_few_images_it_registered(tmp_path):
    r = run("convert", _convert_input(tmp_path, 3), "-o", tmp_path / "two", "--threads", 1)
    assert_one_line_error(r, "registered only 2 of the 9 images", "at least 3")     # (was: exit 0, no word)
    assert not (tmp_path / "two" / "sparse").exists()
    r = run("convert", _convert_input(tmp_path, 4), "-o", tmp_path / "four", "--threads", 1)
    assert r.returncode == 0, r.stderr
    said = warnings(r)
    assert len(said) == 1 and "registered only 4 of the 10 images (40 %)" in said[0], r.stderr
    assert json.loads(r.stdout[r.stdout.index("{"):])["problems"]


def test_focal_lengths_far_apart_are_reported(tmp_path):
    data = tmp_path / "squashed"
    shutil.copytree(DATA / "tiny_colmap", data)
    (data / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 24 16 20.0 41.0 11.5 7.25\n")
    r = run("info", data)
    assert r.returncode == 0 and "factor of 2.05" in json.loads(r.stdout)["camera_problem"]
    assert len(warnings(r)) == 1 and "fx 20 and fy 41" in warnings(r)[0]
    r = run("optimize", data, "-o", tmp_path / "run", *TRAIN, "--quiet")
    assert r.returncode == 0 and len(warnings(r)) == 1 and "not square" in warnings(r)[0], r.stderr


@pytest.mark.parametrize("command", [
    ("optimize", DATA / "tiny_blender", "--iterations", 2),
    ("render", SCENES / "tiny_gaussians.ply", "--camera", SCENES / "tiny_gaussians_camera.json"),
    ("export", SCENES / "tiny_gaussians.ply"),
    ("points", DATA / "tiny_colmap"),
    ("convert", SCENES / "turntable_images"),
    ("sweep", SCENES / "sweep.toml"),
])
def test_an_empty_output_path_is_refused(command, tmp_path):
    r = run(*command, "-o", "", cwd=tmp_path)
    assert_one_line_error(r, "-o/--output", "empty")
    assert os.listdir(tmp_path) == []                        # (was: the whole run written into the current folder)


# ------------------------------------------------------------------------------------------ nothing silent
def test_long_loads_show_progress(blender, tmp_path):
    now = {"MI_GS_PROGRESS_DELAY": "0"}             # (a bar shows after 2 s; on tiny data, at once)
    r = run("optimize", blender, "-o", tmp_path / "run", *TRAIN, env=now)
    assert r.returncode == 0 and "loading training images" in r.stderr, r.stderr
    r = run("optimize", blender, "-o", tmp_path / "quiet", *TRAIN, "--quiet", env=now)
    assert r.returncode == 0 and "loading training images" not in r.stderr, r.stderr
    r = run("info", blender, env=now)
    assert r.returncode == 0 and "checking images" in r.stderr, r.stderr      # (was: only on a terminal)
    assert "checking images" not in run("info", blender).stderr                # (a short wait says nothing)


@pytest.mark.skipif(not (SHARED / "maryrose").is_dir(), reason="../shared/data/maryrose is not on this machine")
def test_info_on_a_large_dataset_shows_progress_within_seconds():
    proc = subprocess.Popen([EXE, "info", str(SHARED / "maryrose")], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, cwd=tempfile.gettempdir())
    try:
        t, seen = time.perf_counter(), b""
        os.set_blocking(proc.stderr.fileno(), False)
        while b"checking images" not in seen and time.perf_counter() - t < 120 and proc.poll() is None:
            seen += proc.stderr.read() or b""
            time.sleep(0.2)
        # the bar shows while the images are still being checked (was: nothing for 100-250 s, then the answer);
        # no bound in seconds here, which a loaded machine's start-up alone could pass
        assert b"checking images" in seen and proc.poll() is None, seen
    finally:
        proc.kill()
        proc.wait()


# ------------------------------------------------------------------------------ settings with no effect
def test_settings_with_no_effect_in_the_run_say_so(blender, tmp_path):
    r = run("optimize", blender, "-o", tmp_path / "run", *TRAIN, "--quiet", "--set", "optim.pose_opt_lr=0.001",
            "--set", "optim.exposure_grid_lr=0.01", "--exposure", "--views", 5, "--port", 9000)
    assert r.returncode == 0, r.stderr
    said = notes(r)
    for needle in ("--set optim.pose_opt_lr has no effect", "--set optim.exposure_grid_lr has no effect",
                   "--views (scene.views) has no effect", "--port has no effect"):
        assert sum(needle in n for n in said) == 1, (needle, r.stderr)
    assert any("--pose-opt" in n and "pose_opt_lr" in n for n in said)
    assert any("--exposure bilateral" in n and "affine" in n for n in said)
    # none where the setting acts
    r = run("optimize", blender, "-o", tmp_path / "run2", *TRAIN, "--quiet", "--pose-opt", "--set",
            "optim.pose_opt_lr=0.001")
    assert r.returncode == 0 and not [n for n in notes(r) if "has no effect" in n], r.stderr


# --------------------------------------------------------------------------------------------- poor cases
def test_optimize_and_eval_score_the_same_view_of_a_run_without_test_views(refined_run):
    out, _ = refined_run
    r = run("eval", out, "--overwrite")
    assert r.returncode == 0, r.stderr
    said = notes(r)
    assert len(said) == 1 and "no test views" in said[0] and "as metrics.json does" in said[0], r.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    scored = json.loads((out / "eval.json").read_text())
    assert scored["split"] == metrics["split"] == "train (no test views)"
    assert list(scored["views"]) == list(metrics["views"])                # (was: every training view)
    assert scored["mean"]["psnr"] == pytest.approx(metrics["mean"]["psnr"], abs=1e-4)


def test_exposure_runs_print_the_half_image_scores(refined_run):
    out, r = refined_run
    summary = json.loads(r.stdout[r.stdout.index("{"):])
    metrics = json.loads((out / "metrics.json").read_text())
    assert summary["half_image"] == metrics["half_image"]["mean"]
    assert any("compare half_image" in n for n in notes(r)), r.stderr
    assert "pose_translation_error_of_camera_spread" in summary


def test_refined_cameras_missing_or_at_another_resolution_are_said(refined_run, colmap, tmp_path):
    out, _ = refined_run
    run_copy = tmp_path / "run"
    shutil.copytree(out, run_copy)
    # at another -r than the run's: the refined poses, with the resolution's intrinsics (was: silently unrefined)
    r = run("render", run_copy / "point_cloud.ply", "--dataset", colmap, "--split", "train", "-r", 2, "-o",
            tmp_path / "r2")
    assert r.returncode == 0 and any("cameras it refined" in n for n in notes(r)), r.stderr
    # a missing cameras_refined.json: one warning, in render, eval and (its entries) view
    (run_copy / run_folder.REFINED_CAMERAS).unlink()
    for args in (("render", run_copy / "point_cloud.ply", "--dataset", colmap, "--split", "train", "-o",
                  tmp_path / "r1"), ("eval", run_copy, "--overwrite")):
        r = run(*args)
        assert r.returncode == 0, r.stderr
        said = warnings(r)
        assert len(said) == 1 and "cameras_refined.json: missing" in said[0] and "--pose-opt" in said[0], r.stderr


def test_a_damaged_checkpoint_names_what_is_wrong(refined_run, colmap, tmp_path):
    out, _ = refined_run
    with np.load(out / "checkpoints" / "ckpt.npz") as z:
        arrays = dict(z)
    cases = {"param/means": "the array 'param/means' is missing", "adam/scales.v": "'adam/scales.v' is missing",
             "pose/value": "'pose/value' is missing", "meta": "its record 'meta' is missing"}
    for drop, words in cases.items():
        run_copy = tmp_path / drop.replace("/", "_")
        shutil.copytree(out, run_copy)
        np.savez(run_copy / "checkpoints" / "ckpt.npz", **{k: v for k, v in arrays.items() if k != drop})
        r = run("optimize", colmap, "-o", run_copy, "--resume", "--iterations", 9, "--quiet")
        assert_one_line_error(r, "ckpt.npz", "incomplete", words)          # (was: "... ('value')")
    run_copy = tmp_path / "random"
    shutil.copytree(out, run_copy)
    (run_copy / "checkpoints" / "ckpt.npz").write_bytes(np.random.default_rng(0).bytes(5000))
    r = run("optimize", colmap, "-o", run_copy, "--resume", "--iterations", 9, "--quiet")
    assert_one_line_error(r, "ckpt.npz", "not a checkpoint of mi-gs")
    assert "pickle" not in r.stderr                                        # (was: NumPy's advice on pickles)


def test_a_bad_setting_is_named_before_what_the_folder_holds(white_run, blender):
    r = run("optimize", blender, "-o", white_run, "--set", "optim.nosuch=1", "--quiet")
    assert_one_line_error(r, "optim.nosuch", "no such field")              # (was: "holds an earlier run")


def test_view_of_a_run_still_training_says_so(white_run, tmp_path):
    folder = tmp_path / "training"
    folder.mkdir()
    shutil.copy(white_run / run_folder.CONFIG, folder / run_folder.CONFIG)
    with run_folder.RunLock(folder):                 # (what a live run holds while it trains)
        r = run("view", folder, "--port", _free_port())
    assert_one_line_error(r, "still training", "mi-gs optimize --view")  # (was: "is it an ... output folder?")


def test_a_scene_of_gaussians_alone_points_at_init_random(tmp_path):
    r = run("optimize", SCENES / "tiny_gaussians.xml", "-o", tmp_path / "run", "-r", 32, "--views", 2,
            "--test-views", 1, "--spp", 1, "--iterations", 3, "--quiet")
    assert_one_line_error(r, "tiny_gaussians.xml", "--init random")


def test_render_of_a_runs_model_takes_the_runs_background_and_resolution(white_run, blender, tmp_path):
    from PIL import Image

    r = run("render", white_run / "point_cloud.ply", "--dataset", blender, "-o", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    said = notes(r)
    assert len(said) == 1 and "-r 2" in said[0] and "--background 1 1 1" in said[0], r.stderr
    name = sorted((blender / "test").glob("*.png"))[0].name
    full = Image.open(blender / "test" / name)
    out = np.asarray(Image.open(tmp_path / "out" / name).convert("RGB"), np.float32)
    assert out.shape[:2] == (full.size[1] // 2, full.size[0] // 2)          # (was: full size)
    r = run("render", white_run / "point_cloud.ply", "--dataset", blender, "-o", tmp_path / "given", "-r", 2,
            "--background", 0)
    assert r.returncode == 0 and not notes(r), r.stderr
    black = np.asarray(Image.open(tmp_path / "given" / name).convert("RGB"), np.float32)
    assert out.mean() > black.mean() + 50                                   # (was: on black)


def test_lengths_have_one_name_each(blender):
    info = json.loads(run("info", blender).stdout)
    assert info["camera_spread"] == info["extent"] and info["length_scale"] == info["scene_extent"]
    assert info["length_scale_rule"] == "depth"
