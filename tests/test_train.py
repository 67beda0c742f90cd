"""Training end to end on a small synthetic Blender-layout scene: PSNR rises, outputs exist, resume is exact,
divergence keeps the last good checkpoint, and bad datasets are refused before training starts."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

import mi_gaussians as mig
from mi_gaussians.config import DataConfig, DensifyConfig, OptimConfig, TrainConfig
from synthetic_dataset import make_blender_dataset


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_blender_dataset(tmp_path_factory.mktemp("synthetic") / "scene")


def small_config(iterations=300, **kw) -> TrainConfig:
    return TrainConfig(
        data=DataConfig(background=(1.0, 1.0, 1.0), random_points=5000),
        optim=OptimConfig(iterations=iterations, position_lr_max_steps=iterations, sh_degree=1,
                          sh_increase_interval=100),
        # (the reference's rules, whatever the default: the images have alpha, but on this schedule the
        # large-Gaussian prunes begin at 150, while the model is still mostly its random points, and the
        # empty-background screen-size prune of 0.1 removes them before they split: 25.7 -> 15.3 dB in
        # test_psnr_rises_and_outputs_are_written; test_an_object_on_an_empty_background_gets_its_rules checks them)
        densify=DensifyConfig(densify_from_iter=100, densify_until_iter=iterations // 2, densification_interval=50,
                              opacity_reset_interval=150, prune_large_after=150, max_screen_fraction=0.0,
                              empty_background="off"),
        checkpoint_every=kw.pop("checkpoint_every", 100), eval_every=100, save_iterations=(), **kw)


def load(scene, cfg):
    d = cfg.data
    return mig.load_dataset(scene, background=d.background, random_points=d.random_points, seed=d.seed)


def test_psnr_rises_and_outputs_are_written(scene, tmp_path):
    from mi_gaussians.optim.trainer import Trainer

    cfg = small_config(600)
    ds = load(scene, cfg)
    tr = Trainer(ds, cfg, tmp_path / "run", progress=False)
    before = tr._test_psnr()
    metrics = tr.run()
    after = metrics["mean"]["psnr"]
    # stated margin: from random points (about 7.5 dB) to at least 22 dB and +12 dB in 600 iterations
    # (measured: 25.7 dB; the curve passes 20 dB near iteration 300)
    assert after > before + 12.0, (before, after)
    assert after > 22.0, after
    out = tmp_path / "run"
    for name in ("point_cloud.ply", "metrics.json", "config.json", "curves.png", "history.json",
                 "checkpoints/ckpt.npz"):
        assert (out / name).exists(), name
    assert len(list((out / "renders").glob("*.exr"))) == len(ds.test)
    assert len(list((out / "compare").glob("*.png"))) == len(ds.test)
    m = json.loads((out / "metrics.json").read_text())
    assert m["gaussians"] == mig.Gaussians.load_ply(out / "point_cloud.ply").n
    assert set(m["views"]) == {v.name for v in ds.test}
    assert m["iterations_per_second"] > 0
    assert m["extent"] == pytest.approx(ds.scene_extent(cfg.data.extent), rel=1e-5)
    # where the time went: the parts of the training time add up to it, and the loop's counts are the run's
    loop, refining = m["loop"], [s for s in range(1, 601) if tr.strategy.refines_at(s)]
    assert sum(loop["seconds"].values()) == pytest.approx(m["training_seconds"], abs=0.01)
    assert loop["seconds"]["other"] < 0.25 * m["training_seconds"], loop
    assert loop["recordings"] == tr.train_step.recordings >= 1 and loop["seconds"]["recording"] > 0
    # (+ the first, and one after each new tile grid: it measures the instances the frozen steps need room for)
    assert len(refining) == 4 and loop["refinements"] == 4 and loop["traced"] == 1 + 4 + loop["regrids"]
    assert loop["replayed"] >= loop["overflows"] >= 0 and loop["syncs"] > 0
    assert loop["outside"]["evaluation"] > 0 and loop["outside"]["saving"] > 0


def test_checkpoint_round_trip_is_exact(scene, tmp_path):
    """Everything a run needs to continue comes back bit-identical from the checkpoint."""
    from mi_gaussians.model.gaussians import PARAMETER_NAMES
    from mi_gaussians.optim.schedules import expon_lr
    from mi_gaussians.optim.trainer import Trainer

    cfg = small_config(230, checkpoint_every=230)      # statistics gathered since the densification at 200
    cfg = dataclasses.replace(cfg, densify=dataclasses.replace(cfg.densify, densify_until_iter=400))
    a = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    a.run()
    b = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    b.load_checkpoint()
    assert b.step == a.step == 230 and b.params.n == a.params.n
    for k, v in a.gaussians.numpy().items():
        np.testing.assert_array_equal(b.gaussians.numpy()[k], v, err_msg=k)
    sa, sb = a.params.export_moments(), b.params.export_moments()
    assert sa.keys() == sb.keys() == {f"{k}.{f}" for k in PARAMETER_NAMES for f in "tmv"}
    assert sa["means.t"][0] > 100 and np.abs(sa["means.m"]).max() > 0
    for k in sa:
        np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)
    (da, ma), (db, mb) = a.strategy.export_state(a.strategy_state), b.strategy.export_state(b.strategy_state)
    assert da.keys() == db.keys() == {"grad_accum", "denom", "max_screen", "reset_done"} and da["denom"].max() > 0
    for k in da:
        np.testing.assert_array_equal(da[k], db[k], err_msg=k)
    assert ma == mb and ma["draws"] > 0
    assert a.sampler.state() == b.sampler.state()
    assert a.bg_rng.bit_generator.state == b.bg_rng.bit_generator.state
    assert a.history.to_dict() == b.history.to_dict()
    la, lb = a.loop.to_dict(), b.loop.to_dict()
    assert la.pop("outside")["saving"] > lb.pop("outside")["saving"]     # (the checkpoint's own writing)
    assert la == lb and la["traced"] > 1
    # the next iteration continues identically: same view, same scheduled position rate, same update
    from mi_gaussians.drjit_utils import exact_float_math

    with exact_float_math():                    # (as Trainer.advance traces them)
        a._iteration(231)
        b._iteration(231)
    o = cfg.optim
    lr = a.extent * expon_lr(231, o.position_lr_init, o.position_lr_final, o.position_lr_max_steps)
    assert a.params.learning_rate("means") == b.params.learning_rate("means") == pytest.approx(lr)
    for k, v in a.gaussians.numpy().items():
        np.testing.assert_allclose(b.gaussians.numpy()[k], v, rtol=1e-5, atol=1e-7, err_msg=k)


def test_kill_9_then_resume_ends_at_the_same_quality(scene, tmp_path):
    """``mi-gs optimize`` killed with SIGKILL after a checkpoint, then ``--resume``: it finishes, and its test
    PSNR matches an uninterrupted run (two runs are not bit-identical anyway: parallel float reductions)."""
    import signal
    import subprocess
    import sys
    import tempfile
    import time

    exe = str(Path(sys.executable).parent / "mi-gs")
    # (densifying from 100: the checkpoints at 100, 200, ... are refinement iterations, whose refinement a checkpoint
    # holds as pending and the resumed run applies first)
    args = ["optimize", str(scene), "--iterations", "600", "--white-background", "--sh-degree", "1",
            "--checkpoint-every", "100", "--eval-every", "0", "--quiet", "--random-points", "5000"]
    new = ["--set", "densify.densify_from_iter=100"]         # (a resumed run takes its settings from config.json)
    out = tmp_path / "killed"
    proc = subprocess.Popen([exe, *args, *new, "-o", str(out)], cwd=tempfile.gettempdir(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    ckpt = out / "checkpoints" / "ckpt.npz"
    deadline = time.time() + 240
    step = 0
    while time.time() < deadline and proc.poll() is None:
        if ckpt.exists():
            try:
                with np.load(ckpt) as z:
                    step = json.loads(bytes(z["meta"]).decode())["step"]
            except Exception:   # being replaced right now
                step = 0
            if step >= 200:
                break
        time.sleep(0.05)
    assert proc.poll() is None, "the run finished before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (out / "point_cloud.ply").exists()
    res = subprocess.run([exe, *args, "-o", str(out), "--resume"], cwd=tempfile.gettempdir(), capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    resumed = json.loads((out / "metrics.json").read_text())
    assert resumed["iterations"] == 600
    res = subprocess.run([exe, *args, *new, "-o", str(tmp_path / "straight")], cwd=tempfile.gettempdir(),
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    straight = json.loads((tmp_path / "straight" / "metrics.json").read_text())
    assert abs(resumed["mean"]["psnr"] - straight["mean"]["psnr"]) < 0.5, (resumed["mean"], straight["mean"])
    # the loop's counts carried over: the same refinements, and one more traced iteration (the first after resuming)
    assert resumed["loop"]["refinements"] == straight["loop"]["refinements"] > 0
    assert resumed["loop"]["traced"] == straight["loop"]["traced"] + 1


@pytest.mark.parametrize("freeze", [True, False])
def test_divergence_stops_and_keeps_the_checkpoint(scene, tmp_path, freeze):
    """A NaN colour before iteration 45 stops the run at 45, frozen (detected at the next read of the flags,
    iteration 45 and the queued ones after it masked) or traced; the checkpoint of iteration 40 stays."""
    from mi_gaussians.optim.trainer import Trainer, TrainingDiverged

    cfg = dataclasses.replace(small_config(60, checkpoint_every=20), freeze=freeze)
    tr = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    orig = tr.advance

    def poisoned():
        if tr.step + 1 == 45:
            import drjit as dr
            import mitsuba as mi

            shape = tuple(tr.params["sh_dc"].shape)
            tr.params.replace("sh_dc", mi.TensorXf(dr.full(mi.Float, float("nan"), int(np.prod(shape))), shape))
        return orig()

    tr.advance = poisoned
    with pytest.raises(TrainingDiverged, match=r"loss became nan at iteration 45\b"):
        tr.run()
    ckpt = tmp_path / "run" / "checkpoints" / "ckpt.npz"
    with np.load(ckpt) as z:
        meta = json.loads(bytes(z["meta"]).decode())
        assert meta["step"] == 40
        assert np.all(np.isfinite(z["param/sh_dc"]))


def test_an_object_on_an_empty_background_gets_its_rules(scene, tmp_path):
    """densify.empty_background 'auto' turns the empty-background rules on when a training image has transparent
    pixels (the synthetic scene's RGBA images), not on the same images made opaque; 'on' and 'off' force them."""
    from PIL import Image

    from mi_gaussians.optim.trainer import Trainer

    def rules(root, setting, background=(0.0, 0.0, 0.0)):
        cfg = small_config(20)
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, background=background),
                                  densify=dataclasses.replace(DensifyConfig(), empty_background=setting))
        tr = Trainer(load(root, cfg), cfg, tmp_path / f"run_{setting}_{root.name}", progress=False)
        return tr.empty_background, tr.strategy.screen_fraction, tr.strategy.refines_at(500)

    assert rules(scene, "auto") == (True, 0.1, True)          # (the reset at densify_from_iter, on black)
    assert rules(scene, "off") == (False, 0.0, False)
    assert rules(scene, "off", (1.0, 1.0, 1.0)) == (False, 0.0, True)    # (the reference's reset on white)
    import shutil
    opaque = tmp_path / "opaque"
    shutil.copytree(scene, opaque)
    for png in opaque.rglob("*.png"):
        Image.open(png).convert("RGB").save(png)
    assert rules(opaque, "auto") == (False, 0.0, False)
    assert rules(opaque, "on") == (True, 0.1, True)
    # a new run says so in one line (what it does, and the setting that gives the reference's rules)
    from mi_gaussians.runs import train_run

    def said(densify, name):
        lines = []
        cfg = small_config(40)
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, background=(0.0, 0.0, 0.0), init="cube"),
                                  densify=densify)
        train_run(scene, tmp_path / name, cfg, progress=False, log=lines.append)
        return [ln for ln in lines if "empty background" in ln]

    short = DensifyConfig(densify_from_iter=5, densification_interval=5, densify_until_iter=35, prune_large_after=15,
                          screen_prune_span=10)
    assert said(short, "said") == [
        "an object on an empty background (the training images have transparent pixels): an opacity reset at "
        "iteration 5 and the screen-size prune at 0.1 of the image at iterations 20-25 (densify.empty_background=off: "
        "the reference's rules)"]
    # (what does not fall within the run is not promised: the defaults' reset at 500 and prunes after 3000)
    assert said(DensifyConfig(), "said_default") == [
        "an object on an empty background (the training images have transparent pixels): no opacity reset at "
        "densify.densify_from_iter within the run and no screen-size prune within the run "
        "(densify.empty_background=off: the reference's rules)"]


def test_random_background_recomposites_rgba_targets(scene, tmp_path):
    from PIL import Image

    from mi_gaussians.optim.trainer import Trainer

    cfg = small_config(40)
    cfg = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, random_background=True))
    tr = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    rgba = np.asarray(Image.open(tr.ds.train[3].image_path)).astype(np.float32) / 255.0
    bg = (0.2, 0.7, 0.4)
    expect = rgba[..., :3] * rgba[..., 3:] + np.array(bg, np.float32) * (1 - rgba[..., 3:])
    np.testing.assert_allclose(np.array(tr.target(3, bg)), expect, atol=2e-6)
    metrics = tr.run()
    assert np.isfinite(metrics["mean"]["psnr"])


@pytest.mark.parametrize("strategy, random_background", [("default", False), ("default", True), ("mcmc", True)])
def test_no_recompilation_when_the_training_view_changes(scene, tmp_path, strategy, random_background):
    """After a warm-up, training iterations on other views (other cameras of the same size, other targets, other
    background colours, other instance counts, other learning rates and, with MCMC, other noise steps) launch only
    kernels that are already compiled: per-view and per-step values travel as opaque arrays, never as kernel literals.
    Runs on any variant (``pytest --variant cuda_ad_rgb``)."""
    from kernel_log import KernelLog
    from mi_gaussians.optim.trainer import Trainer

    cfg = small_config(1000)
    cfg = dataclasses.replace(cfg, strategy=strategy,
                              optim=dataclasses.replace(cfg.optim, sh_increase_interval=10_000,
                                                        random_background=random_background),
                              densify=dataclasses.replace(cfg.densify, densify_from_iter=10_000),
                              mcmc=dataclasses.replace(cfg.mcmc, refine_start_iter=10_000))
    tr = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    from mi_gaussians.drjit_utils import exact_float_math

    with KernelLog() as log, exact_float_math():            # (the iterations as Trainer.advance traces them)
        for step in range(1, 4):
            tr._iteration(step)
        log.cut()
        for step in range(4, 4 + 2 * len(tr.ds.train)):      # every training view at least once
            tr._iteration(step)
        log.cut()
    assert len(log.windows[1]) > 20
    unseen = log.unseen(1)
    assert not unseen, f"{len(unseen)} of {len(log.windows[1])} kernels not launched in the warm-up: {unseen[:5]}"


def test_bad_dataset_refused_before_training(tmp_path):
    import subprocess
    import sys
    import tempfile

    empty = tmp_path / "empty"
    empty.mkdir()
    exe = Path(sys.executable).parent / "mi-gs"
    res = subprocess.run([str(exe), "optimize", str(empty), "-o", str(tmp_path / "out")], capture_output=True,
                         text=True, cwd=tempfile.gettempdir(), timeout=300)
    assert res.returncode == 2 and "Traceback" not in res.stderr and str(empty) in res.stderr
    assert not (tmp_path / "out" / "checkpoints").exists()


def test_set_overrides_any_setting_and_is_saved(scene, tmp_path):
    import subprocess
    import sys
    import tempfile

    exe = str(Path(sys.executable).parent / "mi-gs")

    def optimize(*extra):
        return subprocess.run([exe, "optimize", str(scene), "--iterations", "3", "--quiet", "--random-points", "500",
                               "--eval-every", "0", *extra], capture_output=True, text=True,
                              cwd=tempfile.gettempdir(), timeout=600)

    bad = optimize("-o", str(tmp_path / "bad"), "--set", "densify.min_opacty=0.1")
    assert bad.returncode == 2 and "Traceback" not in bad.stderr, bad.stderr
    assert "min_opacty" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "bad" / "checkpoints").exists()

    out = tmp_path / "run"
    res = optimize("-o", str(out), "--set", "densify.min_opacity=0.1", "--set", "optim.feature_lr=0.005",
                   "--white-background", "--set", "data.background=0,0,1")
    assert res.returncode == 0, res.stderr[-2000:]
    train = json.loads((out / "config.json").read_text())["train"]
    assert train["densify"]["min_opacity"] == 0.1 and train["optim"]["feature_lr"] == 0.005
    assert train["data"]["background"] == [0.0, 0.0, 1.0]          # --set is applied after the other options
    assert train["optim"]["iterations"] == 3                          # and leaves them alone
    again = optimize("-o", str(out), "--resume", "--set", "seed=1")
    assert again.returncode == 2 and "--set" in again.stderr and "Traceback" not in again.stderr


@pytest.mark.parametrize("option", ["absgrad", "antialiased"])
def test_quality_options_train(scene, tmp_path, option):
    """--absgrad and --antialiased through the real (frozen) training loop: PSNR rises as in the default mode,
    densification runs on the chosen statistic, and the option is recorded in config.json."""
    from mi_gaussians.optim.trainer import Trainer

    cfg = small_config(300)
    cfg = dataclasses.replace(cfg, densify=dataclasses.replace(cfg.densify, densify_until_iter=260,
                                                               absgrad=option == "absgrad"))
    if option == "antialiased":
        cfg = dataclasses.replace(cfg, raster=dataclasses.replace(cfg.raster, antialiased=True))
    ds = load(scene, cfg)
    tr = Trainer(ds, cfg, tmp_path / "run", progress=False)
    before = tr._test_psnr()
    metrics = tr.run()
    assert metrics["mean"]["psnr"] > before + 8.0, (before, metrics["mean"]["psnr"])
    counts = json.loads((tmp_path / "run" / "history.json").read_text())["gaussians"]
    assert len(set(counts)) > 2, set(counts)              # densification changed the count several times
    saved = json.loads((tmp_path / "run" / "config.json").read_text())["train"]
    assert (saved["densify"]["absgrad"] if option == "absgrad" else saved["raster"]["antialiased"]) is True


@pytest.mark.parametrize("on", [False, True])
def test_adam_step_on_refinement_iterations(scene, tmp_path, on):
    """optim.step_on_refine: a densification iteration takes the Adam step (gsplat's order: Adam, then the
    refinement) or skips it (the reference, whose rebuilt parameters have no gradient there): Adam's step count. The
    refinement itself waits for the start of the next iteration."""
    from mi_gaussians.optim.trainer import Trainer

    cfg = small_config(400)
    cfg = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, step_on_refine=on))
    tr = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    densify_at = 150
    assert tr.strategy.refines_at(densify_at) and not tr.strategy.refines_at(densify_at - 1)
    while tr.step < densify_at - 1 or tr._pending:      # (queued frozen iterations committed; a rewind goes on)
        tr.advance() if tr.step < densify_at - 1 else tr._resolve()
    t_before, n_before = tr.params.moments("means")[0], tr.params.n
    tr.advance()
    assert tr.step == densify_at and tr.params.n == n_before and tr._refine_at == densify_at
    assert tr.params.moments("means")[0] == t_before + int(on)
    tr.advance()                                         # the refinement, then the next iteration steps either way
    tr._resolve()
    assert tr.params.n != n_before and tr._refine_at is None
    assert tr.params.moments("means")[0] == t_before + int(on) + 1


def test_the_trainer_takes_its_lengths_from_data_extent(scene, tmp_path):
    """data.extent reaches every length rule: the same cameras around a dome of points 20 units out (each camera sees
    the far side, about 23 away) train with an extent of that depth under 'scene' and of the cameras' spread under
    'cameras'; the densification boundaries and the position rate follow it."""
    from mi_gaussians.optim.schedules import position_lr
    from mi_gaussians.optim.trainer import Trainer

    base = load(scene, small_config())
    d = np.random.default_rng(0).normal(size=(4000, 3))
    dome = 20.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    ds = dataclasses.replace(base, points_xyz=dome.astype(np.float32), points_rgb=np.full((4000, 3), 0.5, np.float32))
    extents = {}
    for rule in ("scene", "cameras", "depth"):
        cfg = small_config().with_settings([f"data.extent={rule}"])
        tr = Trainer(ds, cfg, tmp_path / rule, progress=False)
        assert tr.extent == ds.scene_extent(rule) and tr.strategy.extent == tr.extent
        assert position_lr(1, cfg.optim, tr.extent) == pytest.approx(position_lr(1, cfg.optim, 1.0) * tr.extent)
        extents[rule] = tr.extent
    assert extents["cameras"] == ds.extent < 5.0
    assert 21.0 < extents["scene"] < 24.0 and extents["depth"] == extents["scene"]
