"""``mi-gs``: the command line. Arguments -> config dataclasses -> library calls.

One module per command (:data:`COMMANDS`), each with ``add_parser(subparsers)`` and ``run(args)``; :mod:`.args`
holds what they share. Every command selects the Mitsuba variant first (``--variant``, before or after the command;
default ``cuda_ad_rgb`` when a CUDA device is present, else ``llvm_ad_rgb``). :func:`main` is the one error boundary:
a problem with the user's input prints one line, ``mi-gs: error: <file or option>: <problem>``, and exits with status
2; nothing is half-written (all outputs are written atomically).

To add a command: a module here with ``add_parser`` and ``run``, and its name in :data:`COMMANDS`.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import sys

from .args import add_variant, set_variant
from .errors import EXIT_INPUT_ERROR, EXIT_INTERRUPTED, InputError, one_line, os_error_line

#: The commands, in the order ``mi-gs -h`` lists them: each a module of this package.
COMMANDS = ("info", "render", "optimize", "sweep", "points", "eval", "export", "view", "convert")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``mi-gs: error: argument --iterations: ... (see mi-gs optimize -h)`` instead
    of the usage block and the error."""

    def error(self, message: str):
        self.exit(EXIT_INPUT_ERROR, f"mi-gs: error: {message} (see {self.prog} -h)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="mi-gs", description="3D Gaussian Splatting as a Mitsuba 3 plugin.")
    add_variant(p)
    sub = p.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        module = importlib.import_module(f"{__name__}.{name}")
        module.add_parser(sub)
        command = sub.choices[name]
        add_variant(command, after_command=True)
        command.set_defaults(handler=module.run)
    return p


def main(argv=None) -> int:
    """The error boundary: every expected failure is one line ``mi-gs: error: ...`` on stderr and exit status 2
    (argparse's own errors included); a diverged run exits 3, Ctrl-C 130."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    try:
        set_variant(args.variant)           # (importing this package registered the plugins for every variant)
        status = args.handler(args)
        sys.stdout.flush()
        return status
    except BrokenPipeError:
        return _broken_pipe()
    except (InputError, ValueError, OSError) as e:
        if isinstance(e, OSError) and e.errno == errno.EPIPE:
            return _broken_pipe()
        return _error(os_error_line(e) if isinstance(e, OSError) else one_line(e))
    except RuntimeError as e:   # Mitsuba reports scene-file problems as RuntimeError
        return _error(one_line(e))
    except KeyboardInterrupt:
        print("mi-gs: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _error(message: str) -> int:
    print(f"mi-gs: error: {message}", file=sys.stderr)
    return EXIT_INPUT_ERROR


def _broken_pipe() -> int:
    # the reader of our output went away (``mi-gs info ... | head``): say so once, and keep Python from
    # complaining again when it flushes stdout at exit
    import os

    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except OSError:
        pass
    return _error("standard output was closed before everything was written (broken pipe)")
