"""The output folder of ``mi-gs optimize`` (a run): the names of its outputs, whether it holds a run, clearing one,
the settings it saved, and where its cached references are.

A run folder holds ``config.json`` (the settings, the dataset and, for a Mitsuba scene, the references folder),
``checkpoints/``, the model ``point_cloud.ply``, metrics and reports, and by default the cached references of a scene
file in ``references/`` (kept when a run is cleared).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

CONFIG = "config.json"
CHECKPOINTS = "checkpoints"
MODEL = "point_cloud.ply"
EVAL = "eval.json"
GAUSSIAN_SCENE = "gaussians.xml"
REFERENCES = "references"
RUN_OUTPUTS = (CHECKPOINTS, "renders", "compare", CONFIG, "metrics.json", EVAL, "history.json", "curves.png",
               GAUSSIAN_SCENE, MODEL)
_SAVED_MODELS = "point_cloud_*.ply"       # the models of TrainConfig.save_iterations


def holds_run(out: Path) -> bool:
    """Whether ``out`` holds an earlier run (a checkpoint)."""
    checkpoints = out / CHECKPOINTS
    return checkpoints.exists() and any(checkpoints.iterdir())


def check_new_run(out: Path, overwrite: bool) -> None:
    """A new run may go into ``out``: it holds none, or ``overwrite`` was asked for (ValueError otherwise)."""
    if holds_run(out) and not overwrite:
        raise ValueError(f"{out}: holds an earlier run (use --resume to continue it, --overwrite to start "
                         "again, or another folder)")


def clear_run(out: Path) -> None:
    """Remove an earlier run's outputs from ``out`` (cached references stay)."""
    for name in RUN_OUTPUTS:
        p = out / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    for p in out.glob(_SAVED_MODELS):
        p.unlink()


def read_saved(out: Path, why: str) -> dict:
    """The record ``config.json`` of the run in ``out``; ``why`` completes the error when it is missing."""
    path = out / CONFIG
    if not path.exists():
        raise ValueError(f"{path}: {why}")
    return json.loads(path.read_text())


def saved_cache(saved: dict | None, out: Path) -> str | None:
    """The cache folder of a run's references: OUTDIR/references when they are there (the folder may have moved),
    else the folder the run recorded; None for a run without references."""
    refs = (saved or {}).get("references")
    if not refs:
        return None
    key = Path(refs).name
    return str(out / REFERENCES) if (out / REFERENCES / key).is_dir() else str(Path(refs).parent)


def saved_key(saved: dict | None) -> str | None:
    """The references key of a run (the name of its references folder); None for a run without references."""
    refs = (saved or {}).get("references")
    return Path(refs).name if refs else None


def references_root(out: Path, cache: str | None) -> Path:
    """Where a run's references are cached: ``cache`` when given, else OUTDIR/references."""
    return Path(cache) if cache else out / REFERENCES
