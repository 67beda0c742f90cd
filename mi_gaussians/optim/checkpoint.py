"""The checkpoint file (``checkpoints/ckpt.npz``): named arrays in sections (``param``, ``adam``, ``densify``,
``exposure``: ``section/name`` in the archive) and a JSON ``meta`` record, written atomically, read back with a
one-line error naming the file when it cannot be resumed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io_utils import atomic_path

#: sections whose floating-point arrays must be finite for the run to continue from them
FINITE = ("param", "adam", "exposure", "pose")


def write(path: Path, sections: dict[str, dict[str, np.ndarray]], meta: dict) -> None:
    """Write a checkpoint atomically; :class:`.guard.TrainingDiverged` (and nothing written) when an array of a
    :data:`FINITE` section holds a non-finite value: no checkpoint does."""
    from .guard import TrainingDiverged

    for name in FINITE:
        for k, v in sections.get(name, {}).items():
            if np.issubdtype(np.asarray(v).dtype, np.floating) and not np.all(np.isfinite(v)):
                raise TrainingDiverged(f"{name} {k!r} became non-finite by iteration {meta.get('step')}; the last "
                                       f"good checkpoint ({path}) is kept")
    arrays = {f"{section}/{k}": v for section, values in sections.items() for k, v in values.items()}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def read(path: Path) -> tuple[dict[str, dict[str, np.ndarray]], dict]:
    """(sections, meta); ValueError, one line naming the file, when it is missing, is no checkpoint (another file,
    random bytes), lacks an array or a record the trainer reads (:data:`REQUIRED_META`, :func:`missing_arrays`), or
    holds non-finite values."""
    import zipfile

    if not path.exists():
        raise ValueError(f"{path}: no checkpoint to resume from")
    cannot = "it cannot be resumed (start a new run: --overwrite)"
    if path.is_file() and not zipfile.is_zipfile(path):       # (np.load would try it as a pickle, and say so)
        raise ValueError(f"{path}: not a checkpoint of mi-gs (not a NumPy .npz archive: damaged, truncated or another "
                         f"file); {cannot}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as e:
        raise ValueError(f"{path}: unreadable checkpoint ({' '.join(str(e).split()) or type(e).__name__}); "
                         f"{cannot}") from None
    if "meta" not in data:
        raise ValueError(f"{path}: the checkpoint is incomplete: its record 'meta' is missing; {cannot}")
    try:
        meta = json.loads(bytes(data.pop("meta")).decode("utf-8"))
    except (ValueError, TypeError) as e:
        raise ValueError(f"{path}: the checkpoint's record 'meta' is not JSON ({e}); {cannot}") from None
    if not isinstance(meta, dict) or (absent := [k for k in REQUIRED_META if k not in meta]):
        what = f"has no {absent[0]!r}" if isinstance(meta, dict) else "is not a JSON object"
        raise ValueError(f"{path}: the checkpoint is incomplete: its record 'meta' {what}; {cannot}")
    sections: dict[str, dict[str, np.ndarray]] = {}
    for key, v in data.items():
        section, _, name = key.partition("/")
        if section in FINITE and v.dtype.kind == "f" and not np.all(np.isfinite(v)):
            raise ValueError(f"{path}: the checkpoint holds non-finite values ({key}); it cannot be resumed "
                             "(start a new run: --overwrite)")
        sections.setdefault(section, {})[name] = v
    if absent := missing_arrays(sections, meta):
        more = f" (and {len(absent) - 1} more)" if len(absent) > 1 else ""
        raise ValueError(f"{path}: the checkpoint is incomplete: the array {absent[0]!r} is missing{more}; {cannot}")
    return sections, meta


#: the entries of a checkpoint's ``meta`` record that resuming reads
REQUIRED_META = ("step", "elapsed", "history", "sampler", "bg_rng", "strategy")


def missing_arrays(sections: dict[str, dict[str, np.ndarray]], meta: dict | None = None) -> list[str]:
    """The arrays of the model and its Adam moments that ``sections`` lacks (``section/name``): every parameter of
    :data:`~mi_gaussians.model.gaussians.PARAMETER_NAMES`, and its moments ``.t``, ``.m``, ``.v`` (``sh_rest``'s only
    when the model has higher SH bands); and the values of the pose corrections and exposure transforms that the
    settings recorded in ``meta`` (``config``) say the run learns."""
    from ..model.gaussians import PARAMETER_NAMES

    param, adam = sections.get("param", {}), sections.get("adam", {})
    out = [f"param/{k}" for k in PARAMETER_NAMES if k not in param]
    for k in PARAMETER_NAMES:
        if k == "sh_rest" and (k not in param or param[k].ndim < 2 or param[k].shape[1] == 0):
            continue
        out += [f"adam/{k}.{m}" for m in ("t", "m", "v") if f"{k}.{m}" not in adam]
    cfg = (meta or {}).get("config")
    optim = cfg.get("optim") if isinstance(cfg, dict) else None
    if isinstance(optim, dict):
        learned = {"pose": optim.get("pose_opt") is True, "exposure": optim.get("exposure") in ("affine", "bilateral")}
        out += [f"{section}/value" for section, on in learned.items()
                if on and "value" not in sections.get(section, {})]
    return out


#: Settings a resumed run may change (``mi-gs optimize --resume --iterations N`` and the like): everything else
#: belongs to the run's identity. (tests/test_divergence_guard.py checks that the command line's resumable options
#: stay inside this set.)
RESUMABLE = ("optim.iterations", "checkpoint_every", "eval_every", "save_iterations")


def check_identity(path: Path, meta: dict, run_id: str | None, cfg, config_path: Path) -> None:
    """ValueError (one line naming ``path``) when the checkpoint was written by another run than the one recorded in
    ``config_path`` (identity ``run_id`` and settings ``cfg``): its run identity differs, or, where either side has
    none (a run of an earlier version), a setting outside :data:`RESUMABLE` differs."""
    from ..config import TrainConfig, setting_items

    theirs = meta.get("run_id")
    if run_id and theirs:
        if theirs != run_id:
            raise ValueError(f"{path}: the checkpoint belongs to another run (run {theirs[:12]}, while "
                             f"{config_path} records run {run_id[:12]}): was it copied from another output folder? "
                             "resume that run in its own folder, or start a new one")
        return
    saved = meta.get("config")
    if not isinstance(saved, dict):
        return                                   # (a checkpoint of the first versions: nothing to compare with)
    try:
        old = dict(setting_items(TrainConfig.from_dict(saved)))
    except Exception as e:                       # (settings no version of mi-gs wrote)
        raise ValueError(f"{path}: the checkpoint's settings cannot be read ({e}); it is not this run's") from None
    now = dict(setting_items(cfg))
    differ = [k for k in sorted(set(old) | set(now)) if k not in RESUMABLE and old.get(k) != now.get(k)]
    if differ:
        k = differ[0]
        raise ValueError(f"{path}: the checkpoint was written with other settings than {config_path} records "
                         f"({k}: {old.get(k)!r} in the checkpoint, {now.get(k)!r} in the record"
                         f"{f', and {len(differ) - 1} more' if len(differ) > 1 else ''}): it is another run's")
