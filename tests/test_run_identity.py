"""A checkpoint knows whose it is (issue 54): ``--resume`` refuses a checkpoint written by another run, in one line,
and never trains someone else's model on.

Each run gets an identity when it starts (config.json's ``run_id``), which every one of its checkpoints carries; a run
or checkpoint of an earlier version, without one, is compared by its settings instead.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from mi_gaussians.optim import checkpoint
from test_cli import assert_one_line_error, run

DATA = Path(__file__).resolve().parent / "data"
SHORT = ["--iterations", "20", "--checkpoint-every", "10", "--eval-every", "0", "--quiet", "--sh-degree", "1"]


def _meta(ckpt: Path) -> dict:
    with np.load(ckpt) as z:
        return json.loads(bytes(z["meta"]).decode())


def _rewrite(ckpt: Path, meta: dict) -> None:
    with np.load(ckpt) as z:
        arrays = {k: z[k] for k in z.files if k != "meta"}
    sections: dict = {}
    for k, v in arrays.items():
        section, name = k.split("/", 1)
        sections.setdefault(section, {})[name] = v
    checkpoint.write(ckpt, sections, meta)


def test_a_checkpoint_from_another_run_is_refused(tmp_path):
    """Its own checkpoint resumes and keeps the identity; another run's, copied in, is refused and nothing changes."""
    a, b = tmp_path / "a", tmp_path / "b"
    assert run("optimize", DATA / "tiny_blender", "-o", a, *SHORT).returncode == 0
    assert run("optimize", DATA / "tiny_colmap", "-o", b, *SHORT).returncode == 0
    ids = [json.loads((r / "config.json").read_text())["run_id"] for r in (a, b)]
    assert ids[0] != ids[1] and all(_meta(r / "checkpoints" / "ckpt.npz")["run_id"] == i for r, i in zip((a, b), ids))
    res = run("optimize", DATA / "tiny_colmap", "-o", b, "--resume", "--iterations", "30", "--quiet")
    assert res.returncode == 0, res.stderr
    assert json.loads((b / "config.json").read_text())["run_id"] == ids[1] == _meta(b / "checkpoints" / "ckpt.npz")["run_id"]

    shutil.copy(a / "checkpoints" / "ckpt.npz", b / "checkpoints" / "ckpt.npz")
    before = (b / "point_cloud.ply").read_bytes()
    res = run("optimize", DATA / "tiny_colmap", "-o", b, "--resume", "--iterations", "40", "--quiet")
    assert_one_line_error(res, "ckpt.npz", "belongs to another run")
    assert (b / "point_cloud.ply").read_bytes() == before


def test_runs_of_earlier_versions_are_compared_by_their_settings(tmp_path):
    """No identity on either side (an earlier version's run): the same settings resume; other ones are refused,
    naming the first that differs."""
    out = tmp_path / "run"
    assert run("optimize", DATA / "tiny_colmap", "-o", out, *SHORT).returncode == 0
    record = json.loads((out / "config.json").read_text())
    del record["run_id"]
    (out / "config.json").write_text(json.dumps(record))
    ckpt = out / "checkpoints" / "ckpt.npz"
    meta = _meta(ckpt)
    del meta["run_id"]
    _rewrite(ckpt, meta)
    res = run("optimize", DATA / "tiny_colmap", "-o", out, "--resume", "--iterations", "30", "--quiet")
    assert res.returncode == 0, res.stderr
    assert json.loads((out / "config.json").read_text())["run_id"]       # (it has one from now on)

    record = json.loads((out / "config.json").read_text())
    del record["run_id"]
    record["train"]["densify"]["grad_threshold"] = 0.0005
    (out / "config.json").write_text(json.dumps(record))
    res = run("optimize", DATA / "tiny_colmap", "-o", out, "--resume", "--iterations", "40", "--quiet")
    assert_one_line_error(res, "ckpt.npz", "densify.grad_threshold", "another run's")


def test_what_resume_may_change_is_outside_the_identity():
    """The command line's options that --resume may change (train_options: an option with a ``resume`` rule) are all
    in checkpoint.RESUMABLE, the one list the identity check leaves out."""
    from mi_gaussians.cli.train_options import options

    resumable = {k for opt in options() if opt.resume is not None for k in opt.keys}
    assert resumable and resumable <= set(checkpoint.RESUMABLE), resumable - set(checkpoint.RESUMABLE)
