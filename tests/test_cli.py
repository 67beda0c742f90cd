"""``mi-gs`` end to end: help, info, render (camera JSON, dataset views, scene XML) and one-line errors."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import mi_gaussians as mig
from mi_gaussians.imwrite import srgb_to_linear

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"


def run(*args):
    """Run the installed ``mi-gs`` (outside the source tree, so the installed package is what runs)."""
    exe = Path(sys.executable).parent / "mi-gs"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-c", "import sys; from mi_gaussians.cli import main; "
                                                                 "sys.exit(main())"]
    return subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True, timeout=600,
                          cwd=tempfile.gettempdir())


def checkpoint_step(out: Path) -> int:
    """The iteration of a run folder's checkpoint, 0 while there is none (or it is being replaced)."""
    try:
        with np.load(out / "checkpoints" / "ckpt.npz") as z:
            return int(json.loads(bytes(z["meta"]).decode())["step"])
    except (OSError, KeyError, ValueError, EOFError):
        return 0


#: What a run says before training as it goes (where its initial points come from) and its notes (a setting with no
#: effect, a fallback, no densification in the run), not part of an error.
PROGRESS_LINES = ("initial points: ", "triangulation [", "note: ")


def message_lines(stderr: str) -> list[str]:
    """The non-empty lines of a command's stderr, without the progress lines of :data:`PROGRESS_LINES`."""
    return [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith(PROGRESS_LINES)]


def assert_one_line_error(res, *needles):
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    err = message_lines(res.stderr)
    assert len(err) == 1 and err[0].startswith("mi-gs: error: "), res.stderr
    assert "Traceback" not in res.stderr
    for n in needles:
        assert n in err[0], (n, err[0])


def test_console_script_installed():
    exe = Path(sys.executable).parent / "mi-gs"
    assert exe.exists() or shutil.which("mi-gs"), "the mi-gs console script is not installed"


def test_help_lists_only_real_subcommands():
    res = run("--help")
    assert res.returncode == 0
    for cmd in ("info", "render", "convert"):
        assert cmd in res.stdout


def test_info_on_ply():
    res = run("info", SCENES / "tiny_gaussians.ply")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert info["gaussians"] == 2000 and info["sh_degree"] == 1


def test_info_on_splat_spz_and_run_folders(tmp_path):
    """mi-gs info reads what mi-gs writes: .splat / .spz models, and a run folder (finished, or stopped with only a
    checkpoint); a damaged .spz is one line naming it."""
    from mi_gaussians.model.ply import read_ply
    from mi_gaussians.model.web_formats import write_model

    p = read_ply(SCENES / "tiny_gaussians.ply")
    for name in ("m.splat", "m.spz"):
        write_model(tmp_path / name, p)
        res = run("info", tmp_path / name)
        assert res.returncode == 0, res.stderr
        info = json.loads(res.stdout)
        assert info["gaussians"] == 2000 and info["format"] == name[2:], info
        assert info["sh_degree"] == (0 if name.endswith("splat") else 1)
    (tmp_path / "bad.spz").write_bytes(b"\x1f\x8b" + b"not gzip at all")
    assert_one_line_error(run("info", tmp_path / "bad.spz"), "bad.spz")
    out = tmp_path / "run"
    r = run("optimize", ROOT / "tests" / "data" / "tiny_colmap", "-o", out, "--iterations", 20, "--quiet",
            "--checkpoint-every", 10)
    assert r.returncode == 0, r.stderr
    # every run writes its cameras, each in the camera JSON format render --camera takes
    cams = json.loads((out / "cameras.json").read_text())
    assert [len(cams["train"]), len(cams["test"])] == [2, 1] and cams["test"][0]["name"]
    (tmp_path / "cam.json").write_text(json.dumps(cams["test"][0]))
    r = run("render", out / "point_cloud.ply", "--camera", tmp_path / "cam.json", "-o", tmp_path / "test.png")
    assert r.returncode == 0 and (tmp_path / "test.png").is_file(), r.stderr
    info = json.loads(run("info", out).stdout)
    assert info["run"] == str(out) and info["finished"] and info["iterations"] == 20
    assert info["checkpoint"]["iteration"] == 20 and info["model"]["gaussians"] == info["checkpoint"]["gaussians"]
    assert info["test"]["psnr"] == json.loads((out / "metrics.json").read_text())["mean"]["psnr"]
    for f in ("metrics.json", "point_cloud.ply"):                  # a run stopped before its end
        (out / f).unlink()
    info = json.loads(run("info", out).stdout)
    assert not info["finished"] and "test" not in info and "model" not in info and info["checkpoint"]["iteration"] == 20
    ckpt = out / "checkpoints" / "ckpt.npz"
    for damaged in (ckpt.read_bytes()[:100], b""):                 # a damaged checkpoint: said, not a traceback
        ckpt.write_bytes(damaged)
        r = run("info", out)
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
        assert json.loads(r.stdout)["checkpoint"]["error"].startswith(f"{ckpt}: not readable")


def test_render_ply_with_camera_json(tmp_path):
    exr, png = tmp_path / "out.exr", tmp_path / "out.png"
    for out in (exr, png):
        res = run("render", SCENES / "tiny_gaussians.ply", "--camera", SCENES / "tiny_gaussians_camera.json",
                  "-o", out, "--background", "1")
        assert res.returncode == 0, res.stderr
        assert out.exists()
    import OpenEXR

    with OpenEXR.File(str(exr)) as f:
        rgb = np.asarray(f.channels()["RGB"].pixels, dtype=np.float32)
    g = mig.Gaussians.load_ply(SCENES / "tiny_gaussians.ply")
    ref = np.array(mig.render(g, mig.Camera.from_json(SCENES / "tiny_gaussians_camera.json"),
                              background=(1, 1, 1)).rgb)
    # the model holds sRGB-encoded colours (like 3DGS models of photos); EXR files are linear
    np.testing.assert_allclose(rgb, srgb_to_linear(ref), atol=1e-5)
    from PIL import Image

    assert Image.open(png).size == (320, 240)


def test_render_scene_xml(tmp_path):
    out = tmp_path / "scene.exr"
    res = run("render", SCENES / "tiny_gaussians.xml", "-o", out)
    assert res.returncode == 0, res.stderr
    assert out.exists() and out.stat().st_size > 1000


def test_render_dataset_views(tmp_path):
    ply = tmp_path / "m.ply"
    shutil.copy(SCENES / "tiny_gaussians.ply", ply)
    ds_dir = ROOT / "tests" / "data" / "tiny_colmap"
    if not ds_dir.exists():
        pytest.skip("tests/data/tiny_colmap fixture missing")
    out = tmp_path / "renders"
    res = run("render", ply, "--dataset", ds_dir, "--split", "all", "-o", out)
    assert res.returncode == 0, res.stderr
    ds = mig.load_dataset(ds_dir)
    assert len(list(out.glob("*.exr"))) == len(ds.views) and len(list(out.glob("*.png"))) == len(ds.views)


def test_malformed_ply_is_one_line_error_and_writes_nothing(tmp_path):
    bad = tmp_path / "bad.ply"
    good = (SCENES / "tiny_gaussians.ply").read_bytes()
    bad.write_bytes(good[: len(good) // 2])            # truncated
    out = tmp_path / "out.png"
    res = run("render", bad, "--camera", SCENES / "tiny_gaussians_camera.json", "-o", out)
    assert_one_line_error(res, str(bad))
    assert not out.exists() and os.listdir(tmp_path) == ["bad.ply"]
    res = run("info", bad)
    assert_one_line_error(res, str(bad))


def test_missing_inputs_and_bad_scene(tmp_path):
    assert_one_line_error(run("render", tmp_path / "nope.ply", "--camera", "x.json", "-o", tmp_path / "o.png"),
                          "nope.ply")
    assert_one_line_error(run("render", SCENES / "tiny_gaussians.ply", "--camera", tmp_path / "cam.json",
                              "-o", tmp_path / "o.png"), "cam.json")
    bad_xml = tmp_path / "bad.xml"
    bad_xml.write_text("<scene version='3.0.0'><shape type='ellipsoids'></scene>")
    assert_one_line_error(run("render", bad_xml, "-o", tmp_path / "o.exr"))
    assert_one_line_error(run("render", SCENES / "tiny_gaussians.ply", "--camera",
                              SCENES / "tiny_gaussians_camera.json", "-o", tmp_path / "o.jpg"), "o.jpg")
    assert not (tmp_path / "o.png").exists() and not (tmp_path / "o.exr").exists()


def test_info_on_scene_xml_takes_parameters(tmp_path):
    res = run("info", SCENES / "objects.xml", "-D", "spp=4")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert info["shapes"] > 0 and info["sensors"]
    assert_one_line_error(run("info", SCENES / "objects.xml", "-D", "nokey"), "KEY=VALUE")
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type='sphere'></scene>")
    assert_one_line_error(run("info", bad), str(bad))


def test_parser_defaults_come_from_the_config():
    from mi_gaussians.cli import build_parser, train_options
    from mi_gaussians.config import ConvertConfig, DataConfig, TrainConfig

    p = build_parser()
    a = p.parse_args(["optimize", "scene", "-o", "out"])
    for scene_file in (False, True):                # a run without options has every default of config.py
        assert train_options.new_run_config(a, scene_file) == TrainConfig()
    assert p.parse_args(["info", "x"]).resolution == DataConfig().resolution
    c, cc = p.parse_args(["convert", "images", "-o", "out"]), ConvertConfig()
    assert (c.camera_model, c.threads, c.max_image_size, c.resize) == (cc.camera_model, cc.num_threads,
                                                                        cc.max_image_size, cc.resize)


def test_run_folder(tmp_path):
    from mi_gaussians import run_folder as rf

    out = tmp_path / "run"
    rf.check_new_run(out, overwrite=False)                     # nothing there yet
    for name in ("checkpoints/ckpt.npz", "point_cloud.ply", "point_cloud_7000.ply", "config.json",
                 "references/abc/train/x.exr"):
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text("x")
    with pytest.raises(ValueError, match="holds an earlier run"):
        rf.check_new_run(out, overwrite=False)
    rf.check_new_run(out, overwrite=True)
    manifest = rf.Manifest(out)
    assert not manifest.entries                          # (no record: nobody's run, nothing of it is ours)
    manifest.claim(["checkpoints", "checkpoints/ckpt.npz", "point_cloud.ply", "point_cloud_7000.ply", "config.json",
                    "references"])
    (out / "notes.txt").write_text("the user's")
    assert sorted(rf.Manifest(out).remove_outputs()) == ["checkpoints", "checkpoints/ckpt.npz", "config.json",
                                                         "point_cloud.ply", "point_cloud_7000.ply"]
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()) == \
        [".mi-gs-manifest.json", "notes.txt", "references/abc/train/x.exr"]
    from mi_gaussians.config import TrainConfig

    record = rf.RunRecord("/data", TrainConfig(), references="/moved/away/abc")
    assert record.references_key == "abc" and rf.RunRecord("/data", TrainConfig()).references_key is None
    assert record.references_cache(out) == str(out / "references")           # found where the run is now
    assert rf.RunRecord("/d", TrainConfig(), references="/elsewhere/def").references_cache(out) == "/elsewhere"
    assert rf.references_root(out, None) == out / "references" and rf.references_root(out, "c") == Path("c")
    with pytest.raises(ValueError, match="nothing to resume"):
        rf.RunRecord.read(tmp_path / "empty", "nothing to resume")
    record.write(out)                                                         # (atomically)
    assert rf.RunRecord.read(out, "missing") == record


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.asarray(next(iter(f.parts[0].channels.values())).pixels, dtype=np.float64)


def test_antialiased_run_is_recorded_and_rendered_that_way(tmp_path):
    """--antialiased reaches the run's config.json; `mi-gs render RUN/point_cloud.ply` then renders anti-aliased by
    itself (a PLY records nothing), --no-antialiased overrides it, a lone copy of the PLY renders plain, and
    --resume refuses to switch the mode."""
    from mi_gaussians.config import RasterConfig

    data = ROOT / "tests" / "data" / "tiny_blender"
    out = tmp_path / "run"
    res = run("optimize", data, "-o", out, "--iterations", 30, "--antialiased", "--quiet", "--random-points", 400,
              "--eval-every", 0)
    assert res.returncode == 0, res.stderr
    assert json.loads((out / "config.json").read_text())["train"]["raster"]["antialiased"] is True
    cam = mig.load_dataset(data).test[0].camera
    cam.to_json(tmp_path / "cam.json")
    ply = out / "point_cloud.ply"
    g = mig.Gaussians.load_ply(ply)
    want = {aa: srgb_to_linear(np.array(mig.render(g, cam, cfg=RasterConfig(antialiased=aa)).rgb))
            for aa in (True, False)}
    assert np.abs(want[True] - want[False]).max() > 1e-3
    shutil.copy(ply, tmp_path / "lone.ply")
    for src, flags, aa in ((ply, (), True), (ply, ("--no-antialiased",), False), (tmp_path / "lone.ply", (), False),
                           (tmp_path / "lone.ply", ("--antialiased",), True)):
        target = tmp_path / f"{src.stem}{len(flags)}{aa}.exr"
        res = run("render", src, "--camera", tmp_path / "cam.json", "-o", target, *flags)
        assert res.returncode == 0, res.stderr
        np.testing.assert_allclose(_read_exr(target), want[aa], atol=1e-5, err_msg=f"{src.name} {flags}")
    res = run("optimize", data, "-o", out, "--resume", "--iterations", 31, "--quiet")     # keeps the run's mode
    assert res.returncode == 0, res.stderr
    assert json.loads((out / "config.json").read_text())["train"]["raster"]["antialiased"] is True
    # a config.json that is not a run record: plain, with a warning; the flag is refused for a scene .xml
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(tmp_path / "lone.ply", other / "m.ply")     # (the model of 30 iterations: want[] is its render)
    (other / "config.json").write_text(json.dumps({"dataset": str(data), "train": {"raster": 3}}))
    res = run("render", other / "m.ply", "--camera", tmp_path / "cam.json", "-o", tmp_path / "other.exr")
    assert res.returncode == 0 and "warning: rendering with the default settings" in res.stderr, res.stderr
    np.testing.assert_allclose(_read_exr(tmp_path / "other.exr"), want[False], atol=1e-5)
    assert_one_line_error(run("render", SCENES / "tiny_gaussians.xml", "-o", tmp_path / "x.exr", "--antialiased"),
                          "applies to a .ply")
    plain = tmp_path / "plain"
    assert run("optimize", data, "-o", plain, "--iterations", 5, "--quiet", "--random-points", 100).returncode == 0
    assert_one_line_error(run("optimize", data, "-o", plain, "--resume", "--antialiased"),
                          "--antialiased gives raster.antialiased = True, the run has False")


def test_the_progress_bar_ends_on_the_last_evaluation(tmp_path):
    """The bar's PSNR at the end is the final evaluation's, the one the JSON printed after it reports (the bar used to
    end on the evaluation before the last)."""
    import re

    data = ROOT / "tests" / "data" / "tiny_blender"
    res = run("optimize", data, "-o", tmp_path / "run", "--iterations", 60, "--eval-every", 20, "--random-points", 400)
    assert res.returncode == 0, res.stderr
    shown = re.findall(r"PSNR=([0-9.]+)", res.stderr)
    final = json.loads(res.stdout[res.stdout.index("{"):])["psnr"]
    history = json.loads((tmp_path / "run" / "history.json").read_text())["test_psnr"]
    assert len(history) == 3 and round(history[-2], 2) != round(final, 2)       # (the last two differ)
    assert shown and shown[-1] == f"{final:.2f}", (shown[-3:], final)


def test_a_run_shorter_than_its_densification_start_says_so(tmp_path):
    """A run that ends before its first densification adds no Gaussians: one line says so, and not otherwise."""
    data = ROOT / "tests" / "data" / "tiny_blender"
    short = run("optimize", data, "-o", tmp_path / "short", "--iterations", 30, "--quiet", "--random-points", 400,
                "--eval-every", 0)
    assert short.returncode == 0, short.stderr
    assert "no densification falls within the 30 iterations (densify.densify_from_iter = " in short.stderr, short.stderr
    assert "the run trains the initial 400 Gaussians and adds none" in short.stderr
    densified = run("optimize", data, "-o", tmp_path / "densified", "--iterations", 30, "--quiet", "--random-points",
                    400, "--eval-every", 0, "--set", "densify.densify_from_iter=10", "--set",
                    "densify.densification_interval=5", "--set", "densify.densify_until_iter=25")
    assert densified.returncode == 0, densified.stderr
    assert "densification" not in densified.stderr, densified.stderr
    # --quiet: no information lines (the initial points were printed before), only the note above and the JSON;
    # without it, the information is there
    info_lines = ("initial points", "triangulation", "rendering", "reusing")
    assert not [ln for ln in densified.stderr.splitlines() if ln.startswith(info_lines)], densified.stderr
    assert not [ln for ln in short.stderr.splitlines() if ln.startswith(info_lines)], short.stderr
    assert json.loads(densified.stdout)["gaussians"] > 0
    loud = run("optimize", data, "-o", tmp_path / "loud", "--iterations", 5, "--random-points", 400, "--eval-every", 0)
    assert loud.returncode == 0 and "initial points: 400 random" in loud.stderr, loud.stderr
