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
    arrays = {f"{section}/{k}": v for section, values in sections.items() for k, v in values.items()}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def read(path: Path) -> tuple[dict[str, dict[str, np.ndarray]], dict]:
    """(sections, meta); ValueError when the file is missing, unreadable or holds non-finite values."""
    if not path.exists():
        raise ValueError(f"{path}: no checkpoint to resume from")
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
        meta = json.loads(bytes(data.pop("meta")).decode("utf-8"))
    except Exception as e:
        raise ValueError(f"{path}: unreadable checkpoint ({e})") from None
    sections: dict[str, dict[str, np.ndarray]] = {}
    for key, v in data.items():
        section, _, name = key.partition("/")
        if section in FINITE and v.dtype.kind == "f" and not np.all(np.isfinite(v)):
            raise ValueError(f"{path}: the checkpoint holds non-finite values ({key}); it cannot be resumed "
                             "(start a new run: --overwrite)")
        sections.setdefault(section, {})[name] = v
    return sections, meta
