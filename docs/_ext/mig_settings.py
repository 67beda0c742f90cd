"""The training settings of ``mi_gaussians.config`` for the documentation: every field of the frozen dataclasses of
:class:`~mi_gaussians.config.TrainConfig`, named as ``--set`` names it (``densify.grad_threshold``), with its type,
default, range and the trailing ``#`` comment that explains it in ``config.py`` (read with :mod:`tokenize`, so the
comments stay the one place where a setting's meaning is written)."""

from __future__ import annotations

import ast
import dataclasses
import io
import tokenize
import typing
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Setting:
    key: str                 # "densify.grad_threshold" (or "seed" for a top-level field)
    section: str             # "densify" ("" for top-level fields)
    name: str
    type: str                # as config.py writes it: "float", "tuple[float, float, float]"
    default: object
    source: str              # the default as config.py writes it ("1.0 / 255.0")
    comment: str             # the field's own comment lines, joined
    joined: str = ""         # the comment of the run of fields it belongs to (a sentence over several fields)
    group: tuple[str, ...] = ()   # the keys of that run (empty: the comment is the field's alone)


def set_text(value) -> str:
    """``value`` spelt as ``--set KEY=VALUE`` reads it back (``TrainConfig.with_settings``)."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return ",".join(set_text(v) for v in value)
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _comments(source: str) -> dict[int, tuple[int, str]]:
    """row -> (column, text) of every comment."""
    out = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            out[tok.start[0]] = (tok.start[1], tok.string[1:].strip())
    return out


def _continues(previous: str, comment: str) -> bool:
    """Whether ``comment`` goes on with the sentence of the previous field's comment: it starts with "...", or it
    starts in lower case after a comment that stopped mid-sentence (on a comma, a colon, "or", "this many")."""
    if not previous:
        return False
    if not comment:
        return previous.endswith("...")
    if comment.startswith("..."):
        return True
    return comment[0].islower() and (previous[-1] in ",:;" or previous.split()[-1] in ("or", "and", "run's", "many"))


def field_comments(path: Path) -> dict[str, dict[str, tuple[str, str]]]:
    """class name -> field name -> (its type as written, its default as written, its comment)."""
    source = path.read_text()
    lines = source.splitlines()
    comments = _comments(source)
    tree = ast.parse(source)
    result: dict[str, dict] = {}
    for cls in tree.body:
        if not isinstance(cls, ast.ClassDef):
            continue
        fields = [s for s in cls.body if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)]
        for i, stmt in enumerate(fields):
            col = stmt.col_offset
            stop = fields[i + 1].lineno if i + 1 < len(fields) else (cls.end_lineno or len(lines)) + 1
            texts = [comments[r][1] for r in range(stmt.lineno, stmt.end_lineno + 1) if r in comments]
            for row in range(stmt.end_lineno + 1, stop):
                line = lines[row - 1]
                if row in comments and not line[:comments[row][0]].strip() and comments[row][0] > col:
                    texts.append(comments[row][1])
                else:
                    break
            result.setdefault(cls.name, {})[stmt.target.id] = (
                ast.get_source_segment(source, stmt.annotation), ast.get_source_segment(source, stmt.value)
                if stmt.value is not None else "", " ".join(texts))
    return result


def settings() -> list[Setting]:
    """Every training setting, section by section in the order of ``TrainConfig`` (top-level fields first)."""
    from mi_gaussians import config

    written = field_comments(Path(config.__file__))
    top: list[Setting] = []
    sections: list[Setting] = []

    def add(owner, section: str, into: list):
        cls = type(owner)
        hints = typing.get_type_hints(cls)
        run: list[Setting] = []
        for f in dataclasses.fields(owner):
            value = getattr(owner, f.name)
            if dataclasses.is_dataclass(value):
                continue
            kind, src, comment = written.get(cls.__name__, {}).get(f.name, (str(hints[f.name]), repr(value), ""))
            s = Setting(key=f"{section}.{f.name}" if section else f.name, section=section, name=f.name,
                        type=kind, default=value, source=src, comment=comment)
            if run and _continues(run[-1].comment if run[-1].comment else (run[-2].comment if len(run) > 1 else ""),
                                  comment):
                run.append(s)
            else:
                _close(run)
                run = [s]
            into.append(s)
        _close(run)

    cfg = config.TrainConfig()
    add(cfg, "", top)
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            add(value, f.name, sections)
    return top + sections


def _close(run: list[Setting]) -> None:
    if len(run) > 1:
        text = " ".join(s.comment for s in run if s.comment).replace("... ...", "...")
        for s in run:
            s.joined, s.group = text, tuple(r.key for r in run)


def section_docs() -> dict[str, tuple[str, str]]:
    """section -> (its dataclass's name, its docstring's first paragraph)."""
    from mi_gaussians import config

    cfg = config.TrainConfig()
    out = {"": ("TrainConfig", (config.TrainConfig.__doc__ or "").strip().split("\n\n")[0])}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            doc = type(value).__doc__ or ""
            if doc.startswith(type(value).__name__ + "("):       # (dataclass's generated signature: no docstring)
                doc = ""
            out[f.name] = (type(value).__name__, " ".join(doc.strip().split("\n\n")[0].split()))
    return out
