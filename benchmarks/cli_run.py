"""Training runs for the benchmarks, through the command line as a user would run them (``mi-gs optimize``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path


def train(src: Path, out: Path, iterations: int, options: list[str], code: Path | None = None) -> dict:
    """``mi-gs optimize src -o out --iterations N options...`` and its ``metrics.json``; a finished run in ``out`` is
    reused, an interrupted one resumed. ``code``: another checkout of mi-gaussians to run instead of the installed
    one (e.g. a ``git worktree`` of an earlier commit, for a before / after comparison in the same session)."""
    if (out / "metrics.json").is_file() and (out / "point_cloud.ply").is_file():
        print(f"{out}: trained already, reused", file=sys.stderr)
        return json.loads((out / "metrics.json").read_text())
    src, out = Path(src).resolve(), Path(out).resolve()
    cmd = [sys.executable, "-m", "mi_gaussians.cli", "optimize", str(src), "-o", str(out), "--iterations",
           str(iterations), "--eval-every", "0", "--quiet", *options]
    if (out / "checkpoints" / "ckpt.npz").is_file():
        # (--resume takes the settings from the run's config.json and refuses --set; the other options are checked
        # against the run's)
        cmd = [a for i, a in enumerate(cmd) if a != "--set" and (i == 0 or cmd[i - 1] != "--set")] + ["--resume"]
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(Path(code).resolve()), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    t0 = time.time()
    # (python -m puts the working folder first on the path: the checkout to run)
    subprocess.run(cmd, check=True, env=env, cwd=None if code is None else Path(code).resolve())
    print(f"{out}: trained in {time.time() - t0:.0f} s", file=sys.stderr)
    return json.loads((out / "metrics.json").read_text())
