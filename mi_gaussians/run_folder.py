"""The output folder of ``mi-gs optimize`` (a run): the names of its outputs, whether it holds a run, clearing one,
the settings it saved, where its cached references are, and the lock that makes it one run's folder.

A run folder holds ``config.json`` (the settings, the dataset and, for a Mitsuba scene, the references folder),
``checkpoints/``, the model ``point_cloud.ply``, metrics and reports, and by default the cached references of a scene
file in ``references/`` (kept when a run is cleared).
"""

from __future__ import annotations

import contextlib
import errno
import os
from dataclasses import dataclass
from pathlib import Path

from .config import TrainConfig
from .setting_values import SettingError

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
EXPOSURE = "exposure.json"               # the training images' colour transforms (--exposure), name -> 3x4
EXPOSURE_GRIDS = "exposure_grids.npz"    # ... their bilateral grids (--exposure bilateral): names, grids
GAUSSIAN_SCENE = "gaussians.xml"
CAMERAS = "cameras.json"                 # the run's training and test cameras ({"train": [...], "test": [...]})
REFINED_CAMERAS = "cameras_refined.json"  # --pose-opt: the training cameras as refined ({"train": [...]})
REFINED_IMAGES = "images_refined.txt"    # ... and as COLMAP's images.txt
REFERENCES = "references"
POINTS = "points"                        # triangulated initial points, cached (kept by --overwrite, as references)
#: The names a run writes at the top of its folder (how a folder of an earlier version, without a Manifest, is read)
RUN_OUTPUTS = (CHECKPOINTS, RENDERS, COMPARE, CONFIG, METRICS, EVAL, HISTORY, CURVES, GAUSSIAN_SCENE, MODEL, EXPOSURE,
               EXPOSURE_GRIDS, CAMERAS, REFINED_CAMERAS, REFINED_IMAGES)
_SAVED_MODELS = "point_cloud_*.ply"       # the models of TrainConfig.save_iterations

LOCK = ".mi-gs.lock"
_WRITTEN_FOLDERS = ("", CHECKPOINTS, RENDERS, COMPARE)     # (where a run's temporary files may be left)


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
        fd = _open_lock(path, os.O_RDWR | os.O_CREAT)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise self._busy(fd_path=path) from None
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

    def _busy(self, fd_path: Path) -> "FolderBusy":
        try:
            holder = fd_path.read_text(errors="replace").strip() or "unknown"
        except OSError:
            holder = "unknown"
        return FolderBusy(f"{self.out}: another mi-gs process (PID {holder}) is using this output folder; wait for "
                          "it to end or choose another folder")

    def check_free(self) -> None:
        """:class:`FolderBusy` when a live process holds the folder's lock (nothing is created or taken): asked
        first, so that a folder in use is described as such, not by what it holds."""
        import fcntl

        path = self.out / LOCK
        try:
            fd = _open_lock(path, os.O_RDONLY)
        except FileNotFoundError:
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            raise self._busy(fd_path=path) from None
        finally:
            os.close(fd)

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


def _open_lock(path: Path, flags: int) -> int:
    """The lock file, never through a symbolic link planted in its place."""
    try:
        return os.open(path, flags | os.O_NOFOLLOW, 0o666)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise ValueError(f"{path}: is a symbolic link; mi-gs does not lock through links (remove it)") from None
        raise


def remove_temporary_files(out: Path) -> list[Path]:
    """Remove the temporary files of interrupted writes from a run folder (call with its lock held: no other process
    writes there, so earlier versions' files, which do not name their process, go too) and from its references
    cache (those of processes that have ended: another run may share the cache); the removed paths."""
    from .io_utils import remove_stale_temporary_files

    removed = []
    for sub in _WRITTEN_FOLDERS:
        removed += remove_stale_temporary_files(Path(out) / sub, unowned=True)
    refs = Path(out) / REFERENCES
    if refs.is_dir() and not refs.is_symlink():
        for key in refs.iterdir():
            for sub in ("", "train", "test"):
                removed += remove_stale_temporary_files(key / sub)
    return [Path(p) for p in removed]


def holds_run(out: Path) -> bool:
    """Whether ``out`` holds an earlier run (a checkpoint)."""
    checkpoints = out / CHECKPOINTS
    return checkpoints.exists() and any(checkpoints.iterdir())


def check_new_run(out: Path, overwrite: bool) -> None:
    """A new run may go into ``out``: it holds none, or ``overwrite`` was asked for (ValueError otherwise)."""
    if holds_run(out) and not overwrite:
        raise ValueError(f"{out}: holds an earlier run (use --resume to continue it, --overwrite to start "
                         "again, or another folder)")


def run_outputs(cfg: TrainConfig, view_names, scene_file: bool) -> list[str]:
    """Every file and folder (relative to the run folder) a run of ``cfg`` writes, its views being ``view_names``
    (those it renders at the end) and ``scene_file`` whether it trains on a Mitsuba scene (``gaussians.xml``)."""
    stems = [Path(n).stem for n in view_names]
    out = [CONFIG, CHECKPOINTS, CHECKPOINT, MODEL, METRICS, HISTORY, CURVES, RENDERS, COMPARE, CAMERAS]
    out += [saved_model(i) for i in cfg.save_iterations if i < cfg.optim.iterations]
    out += [f"{RENDERS}/{s}{ext}" for s in stems for ext in (".exr", ".png")] + [f"{COMPARE}/{s}.png" for s in stems]
    compensation = {"affine": [EXPOSURE], "bilateral": [EXPOSURE_GRIDS]}.get(cfg.optim.exposure, [])
    poses = [REFINED_CAMERAS, REFINED_IMAGES] if cfg.optim.pose_opt else []
    return out + ([GAUSSIAN_SCENE] if scene_file else []) + compensation + poses


class Manifest:
    """What the runs in a folder wrote: ``.mi-gs-manifest.json``, the files and folders (relative paths) a run
    claimed before it wrote them. A run writes only where nothing is, or where the manifest says a run of this folder
    wrote; ``--overwrite`` removes exactly what the manifest lists (never following a symbolic link; a folder only
    once nothing else is left in it); anything else in the folder is the user's and is left alone.

    A run folder of an earlier version (a valid ``config.json`` and a checkpoint, no manifest) is taken as it is:
    its outputs by their names (the cached references included)."""

    FILE = ".mi-gs-manifest.json"

    def __init__(self, out: Path):
        import json

        self.out = Path(out)
        self.path = self.out / self.FILE
        try:
            data = json.loads(self.path.read_text())
            self.entries = set(data["created"]) if isinstance(data.get("created"), list) else set()
        except (OSError, ValueError, TypeError, KeyError):
            self.entries = self._earlier_run()

    def _earlier_run(self) -> set[str]:
        """The outputs of a run of an earlier version of mi-gs (which wrote no manifest), or nothing."""
        try:
            RunRecord.read(self.out, "missing")
        except ValueError:
            return set()
        if not (self.out / CHECKPOINT).is_file():
            return set()
        found = {n for n in (*RUN_OUTPUTS, REFERENCES) if _real(self.out / n)}
        found |= {p.name for p in self.out.glob(_SAVED_MODELS) if _real(p)}
        for folder in (CHECKPOINTS, RENDERS, COMPARE):
            if folder in found:
                found |= {f"{folder}/{p.name}" for p in (self.out / folder).iterdir() if _real(p) and p.is_file()}
        return found

    def owns(self, rel: str) -> bool:
        return rel in self.entries

    def check_free(self, rels) -> None:
        """Each of ``rels`` is absent or was written by a run of this folder (and is no symbolic link): ValueError
        naming the first that is not."""
        for rel in rels:
            p = self.out / rel
            if p.is_symlink():
                raise ValueError(f"{p}: is a symbolic link, where mi-gs would write; mi-gs neither writes through "
                                 "nor removes links (move it away, or choose another output folder)")
            if os.path.lexists(p) and not self.owns(rel):
                raise ValueError(f"{p}: exists and was not written by mi-gs (no run of this folder lists it); mi-gs "
                                 "writes its outputs there: move it away, or choose another output folder")

    def claim(self, rels) -> None:
        """Record ``rels`` as written by a run of this folder (atomically, before they are written)."""
        import json

        from .io_utils import atomic_write_text

        new = self.entries | set(rels)
        if new != self.entries or not self.path.is_file():
            self.entries = new
            atomic_write_text(self.path, json.dumps({"created": sorted(new)}, indent=1) + "\n")

    def remove_outputs(self, keep=(REFERENCES, POINTS)) -> list[str]:
        """Remove what the manifest lists (but ``keep`` and what lies below it): files that are files (no links),
        then folders left empty, deepest first. Returns the removed paths (relative)."""
        import json

        from .io_utils import atomic_write_text

        removed = []
        for rel in sorted(self.entries, key=lambda r: (-r.count("/"), r)):
            if any(rel == k or rel.startswith(k + "/") for k in keep):
                continue
            p = self.out / rel
            try:
                if p.is_symlink() or not p.exists():
                    pass
                elif p.is_dir():
                    p.rmdir()                 # (only once empty: a file of the user's keeps it)
                else:
                    p.unlink()
                removed.append(rel)
            except OSError:
                continue
        self.entries -= set(removed)
        atomic_write_text(self.path, json.dumps({"created": sorted(self.entries)}, indent=1) + "\n")
        return removed


    def discard_if_unused(self) -> None:
        """Remove the manifest (and the empty folders it lists) when the run wrote nothing else: a run refused
        after its claim leaves no trace."""
        if not self.path.is_file():
            return
        for rel in sorted(self.entries, key=lambda r: -r.count("/")):
            p = self.out / rel
            if p.is_dir() and not p.is_symlink() and not any(p.iterdir()):
                p.rmdir()
            elif os.path.lexists(p):
                return
        self.path.unlink()


def _real(p: Path) -> bool:
    """``p`` exists and is not a symbolic link."""
    return p.exists() and not p.is_symlink()


@dataclass(frozen=True)
class RunRecord:
    """A run's record, ``config.json``: what it was trained on and with which settings. Written by the trainer when
    a run starts (and again when it resumes), read by ``--resume``, ``eval``, ``render`` and ``view``."""

    dataset: str                            # the dataset folder or scene file it trains on (absolute)
    train: TrainConfig                      # its settings
    dataset_fingerprint: str | None = None  # the content of a dataset folder (``data.dataset.fingerprint``)
    references: str | None = None           # the folder of a scene file's path-traced references (absolute)
    run_id: str | None = None               # the run's identity, also in each of its checkpoints (none: a run of an
                                            # earlier version)

    def to_dict(self) -> dict:
        d = {"dataset": self.dataset}
        d.update({k: v for k, v in (("dataset_fingerprint", self.dataset_fingerprint),
                                    ("references", self.references), ("run_id", self.run_id)) if v is not None})
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
        unknown = sorted(set(saved) - {"dataset", "dataset_fingerprint", "references", "run_id", "train"})
        if unknown:
            raise ValueError(f"{path}: key {unknown[0]!r}: not a key of an mi-gs run record (dataset, "
                             "dataset_fingerprint, references, run_id, train)")
        for key in ("dataset_fingerprint", "references", "run_id"):
            if not isinstance(saved.get(key), (str, type(None))) or saved.get(key) == "":
                raise ValueError(f"{path}: key {key!r}: expected a string, got {saved[key]!r}")
        try:
            train = TrainConfig.from_dict(saved["train"])
        except SettingError as e:
            raise ValueError(f"{path}: key {'train.' + e.key!r}: {e.problem}") from None
        return cls(saved["dataset"], train, saved.get("dataset_fingerprint"), saved.get("references"),
                   saved.get("run_id"))

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
