"""Atomic file output: write to a temporary file in the target folder, then rename over the target."""

from __future__ import annotations

import contextlib
import os
import tempfile


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path next to ``path``; on success rename it onto ``path``, on error remove it.

    ``suffix`` keeps the extension that format writers look at (e.g. ``.exr``); defaults to the target's."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    if suffix is None:
        suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp" + suffix, dir=folder)
    os.close(fd)
    umask = os.umask(0)   # mkstemp creates 0600; give the file the permissions a plain open() would
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def read_json_object(path: str | os.PathLike, what: str = "file", expect: str = "a JSON object") -> dict:
    """The JSON object in ``path``; ValueError with one line naming the file otherwise (``what`` names the kind of
    file in the not-found message, ``expect`` what the object should hold)."""
    import json

    path = os.fspath(path)
    try:
        with open(path, "r", encoding="utf-8") as f:
            d = json.load(f)
    except FileNotFoundError:
        raise ValueError(f"{path}: {what} not found") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: is a folder, not a {what}") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: malformed JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: malformed JSON (not UTF-8 text)") from None
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected {expect}")
    return d


def _nearest_existing(path: str) -> str:
    p = os.path.abspath(path)
    while not os.path.exists(p):
        parent = os.path.dirname(p)
        if parent == p:
            break
        p = parent
    return p


def _check_creatable(path: str, kind: str) -> None:
    """``path`` does not exist yet: its nearest existing ancestor must be a writable folder."""
    anchor = _nearest_existing(path)
    if not os.path.isdir(anchor):
        raise ValueError(f"{path}: cannot create this {kind}: {anchor} is a file, not a folder")
    if not os.access(anchor, os.W_OK | os.X_OK):
        raise ValueError(f"{path}: cannot create this {kind}: {anchor} is not writable")


def check_output_folder(path: str | os.PathLike) -> None:
    """``path`` can be used as an output folder: an existing writable folder, or creatable (ValueError naming
    the path otherwise). Checked before any work, so that a bad ``-o`` fails at once."""
    path = os.fspath(path)
    if os.path.exists(path):
        if not os.path.isdir(path):
            raise ValueError(f"{path}: is a file, not a folder (the output must be a folder)")
        if not os.access(path, os.W_OK | os.X_OK):
            raise ValueError(f"{path}: the output folder is not writable")
        return
    _check_creatable(path, "output folder")


def check_output_file(path: str | os.PathLike) -> None:
    """``path`` can be written as an output file: not a folder, in a writable (or creatable) folder."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a folder, not a file (the output is an image file)")
    if os.path.exists(path):
        folder = os.path.dirname(os.path.abspath(path))
        if not os.access(folder, os.W_OK | os.X_OK):
            raise ValueError(f"{path}: its folder is not writable")
        return
    _check_creatable(path, "output file")
