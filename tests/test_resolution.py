"""Training quality does not fall with the image size (opt-in: ``pytest -m slow``, about 15 minutes on 2 cores).

The same scene, path-traced by Mitsuba at two film sizes, trained by ``mi-gs optimize`` from SIFT points triangulated
with the scene's cameras (``--init triangulate``: the points a COLMAP capture starts from; full structure from motion
registers this synthetic scene's cameras unreliably, 3 of 55 agreeing at 200 pixels, and is refused) with the same
compressed schedule: the larger image must score at least as well
as the smaller one, less a margin. A rule of the trainer stated in pixels fails it: the screen-size prune of 20 px
(a tenth of a 200-pixel image, a twentieth of a 400-pixel one) pruned a larger share of the Gaussians the larger the
image, so that a 400x400 scene ended 6.9 dB below its own half-resolution run on gsplat's benchmark (issue 35), and
``scenes/objects.xml`` at 400 pixels 12.9 dB below itself at 200 (``benchmarks/resolution.py``, 7k of the 30k
schedule).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCENES = Path(__file__).resolve().parents[1] / "scenes"

#: (small, large) film sizes in pixels. Measured on this test's settings (2026-11-28, de478ef, 2 cores): the defaults
#: 37.60 dB at 200 and 38.53 at 400 (+0.93); a rule in pixels, the 20-px screen-size prune of fec57a1 (given as
#: densify.max_screen_fraction 0.1 at 200 and 0.05 at 400), 37.61 and 37.27 (-0.34), which fails. (From structure
#: from motion's points, before they were refused, fec57a1 scored 37.62 and 33.79, part of that from misplaced points.)
SIZES = (200, 400)
#: the paper's schedule compressed about tenfold (densification from 200 every 50 iterations until 2500 of 3000,
#: opacity resets at 1000 and 2000, the large-Gaussian prunes from 1000 on): every rule acts
SCHEDULE = ["--iterations", "3000", "--set", "densify.densify_from_iter=200",
            "--set", "densify.densification_interval=50", "--set", "densify.densify_until_iter=2500",
            "--set", "densify.opacity_reset_interval=1000", "--set", "densify.prune_large_after=1000"]
#: the larger image may score this much below the smaller one (PSNR in dB): none (the defaults leave 0.93 to spare,
#: the pixel rule misses by 0.34)
MARGIN = 0.0


@pytest.mark.slow
def test_a_larger_image_trains_at_least_as_well_as_a_smaller_one(tmp_path):
    psnr = {}
    for size in SIZES:
        out = tmp_path / f"r{size}"
        cmd = [sys.executable, "-m", "mi_gaussians.cli", "optimize", str(SCENES / "objects.xml"), "-o", str(out),
               "-r", str(size), "--spp", "32", "--white-background", "--init", "triangulate",
               "--cache", str(tmp_path / "references"),
               "--quiet", *SCHEDULE]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        psnr[size] = json.loads((out / "metrics.json").read_text())["mean"]["psnr"]
    small, large = SIZES
    assert psnr[large] >= psnr[small] - MARGIN, psnr
