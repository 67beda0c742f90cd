"""The divergence guard (mi_gaussians/optim/guard.py): every trained quantity -- the Gaussians, their Adam moments,
pose corrections, exposure compensation -- finite, or the run stops with one line naming what diverged and the
setting that drives it, and no checkpoint past the last good one is written (issue 54).

A NaN pose correction is the case the loss does not show: the camera sees nothing, its loss stays finite, and the
run used to train on and overwrite its good checkpoints with NaN ones.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from test_train import load, scene, small_config  # noqa: F401  (scene is a fixture)


def _poison_at(tr, step: int, what):
    orig = tr.advance

    def poisoned():
        if tr.step + 1 == step:
            what(tr)
        return orig()

    tr.advance = poisoned


def _nan_pose(tr):
    import drjit as dr
    import mitsuba as mi

    t = tr.poses.tensor
    shape = tuple(t.shape)
    tr.poses._adam["pose"] = mi.TensorXf(dr.full(mi.Float, float("nan"), int(np.prod(shape))), shape)


def _nan_moments(tr):
    import drjit as dr
    import mitsuba as mi

    value, promoted, lr, (t, m, v, vmax) = tr.params._adam.state["scales"]
    tr.params._adam.state["scales"] = (value, promoted, lr, (t, m, dr.full(mi.Float, float("nan"), dr.width(v)), vmax))


@pytest.mark.parametrize("freeze, case, poison, pattern", [
    (True, "pose", _nan_pose, r"the camera pose corrections \(--pose-opt\) became non-finite between iterations "
                              r"\d+ and \d+; driven by optim.pose_opt_lr = 0.0001"),
    (False, "moments", _nan_moments, r"the Gaussians' scales became non-finite .*optim.scaling_lr = 0.005"),
])
def test_a_diverged_quantity_stops_the_run_and_keeps_the_last_good_checkpoint(scene, tmp_path, freeze, case,  # noqa: F811
                                                                              poison, pattern):
    from mi_gaussians.optim.trainer import Trainer, TrainingDiverged

    cfg = dataclasses.replace(small_config(90, checkpoint_every=20), freeze=freeze)
    cfg = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, pose_opt=True))
    tr = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False)
    _poison_at(tr, 45, poison)
    with pytest.raises(TrainingDiverged, match=pattern):
        tr.run()
    assert tr.step <= 45 + 25                        # (at once: by the next synchronization)
    with np.load(tmp_path / "run" / "checkpoints" / "ckpt.npz") as z:
        meta = json.loads(bytes(z["meta"]).decode())
        assert meta["step"] == 40
        for k in z.files:
            if z[k].dtype.kind == "f":
                assert np.all(np.isfinite(z[k])), k
    assert not (tmp_path / "run" / "metrics.json").exists()


def test_the_cli_exits_with_the_divergence_status_and_one_line(scene, tmp_path):  # noqa: F811
    """Through ``mi-gs optimize``: exit status 3 (not 2, the bad-input status) and one line on stderr."""
    import mitsuba as mi

    code = (f"import mitsuba as mi\nmi.set_variant({mi.variant()!r})\n"
            "import sys, mi_gaussians.cli as c, mi_gaussians.optim.trainer as t\n"
            "orig = t.Trainer.advance\n"
            "def advance(self):\n"
            "    if self.step + 1 == 30:\n"
            "        import drjit as dr, mitsuba as mi\n"
            "        shape = tuple(self.poses.tensor.shape)\n"
            "        self.poses._adam['pose'] = mi.TensorXf(dr.full(mi.Float, float('nan'), shape[0] * shape[1]), shape)\n"
            "    return orig(self)\n"
            "t.Trainer.advance = advance\n"
            "sys.exit(c.main(sys.argv[1:]))\n")
    res = subprocess.run([sys.executable, "-c", code, "optimize", str(scene), "-o", str(tmp_path / "run"),
                          "--iterations", "80", "--pose-opt", "--checkpoint-every", "10", "--quiet",
                          "--random-points", "2000", "--sh-degree", "1", "--eval-every", "0",
                          "--variant", mi.variant()],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 3, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if "error" in ln]
    assert len(lines) == 1 and "pose corrections" in lines[0] and "optim.pose_opt_lr" in lines[0], res.stderr


def test_rates_a_run_would_diverge_on_are_refused_before_it_starts():
    from mi_gaussians.config import TrainConfig
    from mi_gaussians.setting_values import SettingError

    for setting in ("optim.pose_opt_lr=1e30", "optim.position_lr_init=5", "optim.opacity_lr=inf",
                    "optim.pose_opt_lr_decay=1e9"):
        with pytest.raises(SettingError, match=setting.split("=")[0]):
            TrainConfig().with_settings([setting]).validate()


def test_corrections_that_throw_the_cameras_around_are_reported(scene, tmp_path):  # noqa: F811
    """The largest rate the range allows stays finite but moves the cameras far more than any calibration error:
    metrics.json's pose report says so, naming the setting (and ``mi-gs optimize`` prints it as a note)."""
    from mi_gaussians.optim.trainer import Trainer

    cfg = small_config(60, checkpoint_every=60)
    cfg = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, pose_opt=True, pose_opt_lr=0.1))
    metrics = Trainer(load(scene, cfg), cfg, tmp_path / "run", progress=False).run()
    poses = metrics["poses"]
    assert poses["correction"]["rotation_degrees"] > 10 or poses["correction"]["translation_of_extent"] > 0.2
    assert "optim.pose_opt_lr = 0.1" in poses["note"]
