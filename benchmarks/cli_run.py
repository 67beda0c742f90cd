"""Training runs for the benchmarks, through the command line as a user would run them (``mi-gs optimize``)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path


def train(src: Path, out: Path, iterations: int, options: list[str]) -> dict:
    """``mi-gs optimize src -o out --iterations N options...`` and its ``metrics.json``; a finished run in ``out`` is
    reused, an interrupted one resumed."""
    if (out / "metrics.json").is_file() and (out / "point_cloud.ply").is_file():
        print(f"{out}: trained already, reused", file=sys.stderr)
        return json.loads((out / "metrics.json").read_text())
    cmd = [str(Path(sys.executable).parent / "mi-gs"), "optimize", str(src), "-o", str(out), "--iterations",
           str(iterations), "--eval-every", "0", "--quiet", *options]
    if (out / "checkpoints" / "ckpt.npz").is_file():
        cmd.append("--resume")
    t0 = time.time()
    subprocess.run(cmd, check=True)
    print(f"{out}: trained in {time.time() - t0:.0f} s", file=sys.stderr)
    return json.loads((out / "metrics.json").read_text())
