"""Objects on an empty background keep what they scored (issue 52; opt-in: ``pytest -m slow``, about 12 minutes on 2
cores).

``scenes/objects.xml`` path-traced by Mitsuba from a full sphere of 100 cameras at 200x200 (views from below
included), written as a Blender-layout dataset with Mitsuba's alpha (``benchmarks/scene_blender.py``), trained as a
user would: ``mi-gs optimize DATASET --iterations 7000`` with the defaults (the triangulated points joined by the
random cube's, since the images have alpha; a black background). Large black Gaussians that the cube leaves under the
disk are invisible against the background in most views and hide the cube's underside in the views from below;
before the fix they cost 2.1 dB here (95075dd: 34.05 dB against fec57a1's 36.18). The fix: the rules for an object on
an empty background (``densify.empty_background``, on since the images have transparent pixels: the opacity reset at
``densify_from_iter`` on any background and the screen-size prune at 0.1 of the image; 36.46 dB).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: fec57a1's held-out PSNR on this dataset, and how far below it a run may end (the spread of runs of one rule here
#: is about 0.1 dB; the regression was 2.1)
FEC57A1 = 36.18
MARGIN = 0.4


@pytest.mark.slow
def test_a_full_sphere_object_on_an_empty_background_scores_what_fec57a1_did(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from scene_blender import main as write_scene

    data = tmp_path / "objects_sphere"
    assert write_scene(["objects", "--rig", "sphere", "--size", "200", "--views", "100", "--test-views", "20",
                        "--spp", "64", "--out", str(data), "--cache", str(tmp_path / "references")]) == 0
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "mi_gaussians.cli", "optimize", str(data), "-o", str(out),
                          "--iterations", "7000", "--quiet"], capture_output=True, text=True, timeout=3600,
                         cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    psnr = json.loads((out / "metrics.json").read_text())["mean"]["psnr"]
    assert psnr >= FEC57A1 - MARGIN, psnr
