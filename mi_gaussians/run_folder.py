"""The output folder of ``mi-gs optimize`` (a run): the names of its outputs, whether it holds a run, clearing one,
the settings it saved, where its cached references are, and the lock that makes it one run's folder.

A run folder holds ``config.json`` (the settings, the dataset and, for a Mitsuba scene, the references folder),
``checkpoints/``, the model ``point_cloud.ply``, metrics and reports, and by default the cached references of a scene
file in ``references/`` (kept when a run is cleared).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from .config import SettingError, TrainConfig

CONFIG = "config.json"
CHECKPOINTS = "checkpoints"
CHECKPOINT = f"{CHECKPOINTS}/ckpt.npz"
MODEL = "point_cloud.ply"
METRICS = "metrics.json"
HISTORY = "history.json"
CURVES = "curves.png"
RENDERS = "renders"
COMPARE = "compare"
EVAL = "eval.json"
GAUSSIAN_SCENE = "gaussians.xml"
REFERENCES = "references"
RUN_OUTPUTS = (CHECKPOINTS, RENDERS, COMPARE, CONFIG, METRICS, EVAL, HISTORY, CURVES, GAUSSIAN_SCENE, MODEL)
_SAVED_MODELS = "point_cloud_*.ply"       # the models of TrainConfig.save_iterations

LOCK = ".mi-gs.lock"
# io_utils.atomic_path's temporary files (".<name>.<8 random characters from mkstemp>.tmp<ext>"), left behind when a
# process was killed while writing; looked for only in the folders a run writes
_TEMPORARY = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")
_WRITTEN_FOLDERS = ("", CHECKPOINTS, RENDERS, COMPARE)


def is_temporary_file(name: str) -> bool:
    """Whether ``name`` is that of an interrupted atomic write's temporary file (``io_utils.atomic_path``)."""
    return _TEMPORARY.match(name) is not None


def saved_model(step: int) -> str:
    """The model saved at iteration ``step`` (``TrainConfig.save_iterations``)."""
    return f"point_cloud_{step}.ply"


class FolderBusy(ValueError):
    """Another live process holds the output folder's lock."""


class RunLock:
    """An exclusive advisory lock (``fcntl.flock``) on ``OUTDIR/.mi-gs.lock``, which holds the PID of its owner.

    The operating system releases it when the process ends in any way (``kill -9`` included), so a lock left by a
    dead run is simply taken over. Taken before anything is written into the folder; a second run (or an ``eval``)
    on the same folder gets :class:`FolderBusy` naming the PID that holds it."""

    def __init__(self, out: Path):
        self.out = Path(out)
        self._fd = None

    def acquire(self) -> "RunLock":
        import fcntl

        self.out.mkdir(parents=True, exist_ok=True)
        path = self.out / LOCK
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            raise FolderBusy(f"{self.out}: another mi-gs process (PID {holder}) is using this output folder; "
                             "wait for it to end or choose another folder") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if not same:                # another run removed the folder it gave up while we waited: start again
            os.close(fd)
            return self.acquire()
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release_and_remove_if_empty(self) -> None:
        """Release the lock; first, while still holding it, remove the folder if it holds nothing but the lock
        file (a run refused before it wrote anything leaves no folder behind)."""
        if self._fd is not None:
            with contextlib.suppress(OSError):
                if {p.name for p in self.out.iterdir()} <= {LOCK}:
                    (self.out / LOCK).unlink()
                    self.out.rmdir()
        self.release()

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, 0)
            os.close(self._fd)      # (closing releases the lock; the file stays, as lock files do)
            self._fd = None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def remove_temporary_files(out: Path) -> list[Path]:
    """Remove the temporary files of interrupted atomic writes from a run folder (call with its lock held); the
    removed paths."""
    removed = []
    for sub in _WRITTEN_FOLDERS:
        folder = Path(out) / sub
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            if is_temporary_file(p.name) and p.is_file():
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
                    removed.append(p)
    return removed


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


@dataclass(frozen=True)
class RunRecord:
    """A run's record, ``config.json``: what it was trained on and with which settings. Written by the trainer when
    a run starts (and again when it resumes), read by ``--resume``, ``eval``, ``render`` and ``view``."""

    dataset: str                            # the dataset folder or scene file it trains on (absolute)
    train: TrainConfig                      # its settings
    dataset_fingerprint: str | None = None  # the content of a dataset folder (``data.dataset.fingerprint``)
    references: str | None = None           # the folder of a scene file's path-traced references (absolute)

    def to_dict(self) -> dict:
        d = {"dataset": self.dataset}
        d.update({k: v for k, v in (("dataset_fingerprint", self.dataset_fingerprint),
                                    ("references", self.references)) if v is not None})
        return {**d, "train": self.train.to_dict()}

    def write(self, out: Path) -> None:
        import json

        from .io_utils import atomic_write_text

        atomic_write_text(Path(out) / CONFIG, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def read(cls, out: Path, why: str) -> "RunRecord":
        """The record of the run in ``out``; ``why`` completes the error when there is none. Every key is checked
        (its type, and each setting's range): ValueError naming the file and the key otherwise."""
        from .io_utils import read_json_object

        path = Path(out) / CONFIG
        if not path.exists():
            raise ValueError(f"{path}: {why}")
        saved = read_json_object(path, "run record", "a JSON object (an mi-gs run record)")
        if not isinstance(saved.get("train"), dict):
            raise ValueError(f"{path}: the run record has no training settings (\"train\"); it was not written by "
                             "mi-gs optimize or was edited")
        if not isinstance(saved.get("dataset"), str) or not saved["dataset"]:
            raise ValueError(f"{path}: the run record does not name its dataset (\"dataset\")")
        unknown = sorted(set(saved) - {"dataset", "dataset_fingerprint", "references", "train"})
        if unknown:
            raise ValueError(f"{path}: key {unknown[0]!r}: not a key of an mi-gs run record (dataset, "
                             "dataset_fingerprint, references, train)")
        for key in ("dataset_fingerprint", "references"):
            if not isinstance(saved.get(key), (str, type(None))) or saved.get(key) == "":
                raise ValueError(f"{path}: key {key!r}: expected a string, got {saved[key]!r}")
        try:
            train = TrainConfig.from_dict(saved["train"])
        except SettingError as e:
            raise ValueError(f"{path}: key 'train.{e.key}': {e.problem}") from None
        return cls(saved["dataset"], train, saved.get("dataset_fingerprint"), saved.get("references"))

    @property
    def references_key(self) -> str | None:
        """The key of the run's references (the name of their folder); None for a run without references."""
        return Path(self.references).name if self.references else None

    def references_cache(self, out: Path) -> str | None:
        """The cache folder of the run's references: OUTDIR/references when they are there (the folder may have
        moved), else the folder the run recorded; None for a run without references."""
        key = self.references_key
        if key is None:
            return None
        here = Path(out) / REFERENCES
        return str(here) if (here / key).is_dir() else str(Path(self.references).parent)


def references_root(out: Path, cache: str | None) -> Path:
    """Where a run's references are cached: ``cache`` when given, else OUTDIR/references."""
    return Path(cache) if cache else out / REFERENCES
