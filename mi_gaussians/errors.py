"""Exceptions as one line: what the command line prints after ``mi-gs: error:`` and what a sweep records of a failed
run."""

from __future__ import annotations


def one_line(e: BaseException) -> str:
    """The message of ``e`` on one line (at most three of its lines joined). Dr.Jit/Mitsuba wrap errors raised inside
    custom operations ("... (see above)"): the innermost cause is reported."""
    while (e.__cause__ or e.__context__) is not None and "see above" in str(e):
        e = e.__cause__ or e.__context__
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return " ".join(lines) if len(lines) <= 3 else " ".join(lines[:3]) + " ..."
