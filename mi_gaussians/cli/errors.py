"""The command line's errors and exit statuses. A problem with the user's input is one line on stderr,
``mi-gs: error: <file or option>: <problem>``, and exit status :data:`EXIT_INPUT_ERROR`."""

from __future__ import annotations

import sys

from ..errors import one_line

EXIT_RUNS_FAILED = 1      # a sweep finished, and some of its runs failed (each recorded with its one-line message)
EXIT_INPUT_ERROR = 2      # bad input (a file, an option, a setting): one line naming it; nothing was changed
EXIT_DIVERGED = 3         # the loss or a parameter became NaN/Inf; the run's last good checkpoint is kept
EXIT_INTERRUPTED = 130    # Ctrl-C (128 + SIGINT, as shells report it)


class InputError(Exception):
    """A problem with the user's input, reported as one line."""


def os_error_line(e: OSError) -> str:
    """``[Errno 21] Is a directory: 'x.png'`` -> ``x.png: is a directory``."""
    what = (e.strerror or str(e)).rstrip(".")
    what = what[0].lower() + what[1:] if what else "cannot be written"
    names = [str(n) for n in (e.filename, e.filename2) if n is not None]
    return f"{' -> '.join(names)}: {what}" if names else one_line(e)


def note(line: str) -> None:
    """A note on stderr: ``note: <line>`` (something the user may not expect, e.g. a setting with no effect; kept by
    ``--quiet``)."""
    print(f"note: {line}", file=sys.stderr, flush=True)


def warn(line: str) -> None:
    """A warning on stderr: ``mi-gs: warning: <line>`` (the command goes on)."""
    print(f"mi-gs: warning: {line}", file=sys.stderr, flush=True)
