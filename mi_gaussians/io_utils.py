"""Atomic file output: write to a temporary file in the target folder, then rename over the target.

A temporary file is named ``.<target name>.<PID>-<8 random characters>.tmp<extension>``: a process killed while
writing leaves one behind, and :func:`remove_stale_temporary_files` removes those whose process is gone (never a file
of another name, never one of a live process). An error while writing names the target, not the temporary file.
"""

from __future__ import annotations

import contextlib
import errno as _errno
import os
import re
import tempfile

# ".<name>.<pid>-<8 characters from mkstemp>.tmp<ext>"; earlier versions wrote ".<name>.<8 characters>.tmp<ext>"
_TEMPORARY = re.compile(r"^\..+\.(?:(?P<pid>\d+)-)?[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")


def is_temporary_file(name: str) -> bool:
    """Whether ``name`` is that of a temporary file of :func:`atomic_path` (this version's or an earlier one's)."""
    return _TEMPORARY.match(name) is not None


def process_alive(pid: int) -> bool:
    """Whether the process ``pid`` is running (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:           # (another user's live process)
        return True
    return True


def remove_stale_temporary_files(folder: str | os.PathLike, unowned: bool = False) -> list[str]:
    """Remove the temporary files in ``folder`` (not below it) whose writing process has ended; ``unowned``: also
    those of earlier versions, which do not name their process (only when the caller knows no other process writes
    there, e.g. it holds the folder's lock). Returns the removed paths."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        m = _TEMPORARY.match(entry.name)
        if m is None or not entry.is_file(follow_symlinks=False):
            continue
        pid = m.group("pid")
        if (pid is None and not unowned) or (pid is not None and (int(pid) == os.getpid() or process_alive(int(pid)))):
            continue
        with contextlib.suppress(FileNotFoundError):
            os.remove(entry.path)
            removed.append(entry.path)
    return removed


def _naming(e: OSError, target: str) -> OSError:
    """``e`` as an OSError naming ``target`` (the file being written), not the temporary file; a short write
    (NumPy's "N requested and M written") says what it most likely is."""
    text = e.strerror or str(e)
    m = re.search(r"(\d+) requested and (\d+) written", str(e))
    if m:
        return OSError(e.errno or _errno.ENOSPC, f"could not be written completely ({m.group(1)} bytes to write, "
                                                 f"{m.group(2)} written: is the disk full?)", target)
    return OSError(e.errno, text, target)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path next to ``path``; on success rename it onto ``path``, on error remove it. Renaming
    replaces a symbolic link at ``path`` itself, never the file it points to.

    ``suffix`` keeps the extension that format writers look at (e.g. ``.exr``); defaults to the target's."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
        if suffix is None:
            suffix = os.path.splitext(path)[1]
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.{os.getpid()}-", suffix=".tmp" + suffix,
                                   dir=folder)
    except OSError as e:
        raise _naming(e, path) from None
    os.close(fd)
    umask = os.umask(0)   # mkstemp creates 0600; give the file the permissions a plain open() would
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        if isinstance(e, OSError):
            raise _naming(e, path) from None
        if isinstance(e, (RuntimeError, ValueError)) and tmp in str(e):     # (e.g. OpenEXR's errors)
            raise type(e)(str(e).replace(tmp, path)) from None
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
