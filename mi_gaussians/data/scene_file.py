"""Loading a Mitsuba scene file with its ``-D KEY=VALUE`` parameters, and the files it references.

Problems with the scene file (missing, XML syntax error, a referenced file missing, no shapes, an empty or infinite
bounding box) raise ``ValueError`` with one line naming the file.
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

_PARAMETER_NAME = r"[A-Za-z_][A-Za-z0-9_]*"


def is_scene_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a Mitsuba scene file (``.xml``), as opposed to a dataset folder or a model."""
    return Path(path).suffix.lower() == ".xml"


def parse_defines(defines) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` (Mitsuba's ``-D KEY=VALUE``) -> ``{KEY: VALUE}``."""
    out = {}
    for d in defines or ():
        key, sep, value = str(d).partition("=")
        if not sep or not key.strip() or not re.fullmatch(_PARAMETER_NAME, key.strip()):
            raise ValueError(f"scene parameter {d!r}: expected KEY=VALUE (as Mitsuba's -D KEY=VALUE)")
        out[key.strip()] = value
    return out


def _mitsuba_message(e: RuntimeError, path: Path) -> str:
    """Mitsuba's error as one line that keeps its cause: the "[parser.cpp:...]" prefixes dropped, a list under a
    heading joined to it ("Found unused parameters: $nosuch=1"), and of nested errors ("while processing
    <include>:" then the included file's problem) the innermost one, without repeating ``path``."""
    lines = [re.sub(r"^\[[^\]]*\]\s*", "", ln).strip() for ln in str(e).strip().splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        return "cannot load"
    items = [ln[1:].strip() for ln in lines[1:] if ln.startswith("- ")]
    if lines[0].endswith(":") and items and len(items) == len(lines) - 1:
        text = f"{lines[0]} {', '.join(items)}"
    else:
        text = lines[-1]
    for where in (str(path), str(path.resolve())):
        text = text.replace(f"Error while loading {where} ", "")
    return re.sub(r"^\((line \d+, col \d+)\):", r"\1:", text)


def load_file(path: str | os.PathLike, defines=()):
    """``mi.load_file`` with one-line errors naming the file (Mitsuba's "[parser.cpp:...]" prefix removed).

    ``defines``: ``"KEY=VALUE"`` strings that set the scene's ``<default name="KEY" .../>`` parameters."""
    import mitsuba as mi

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: scene file not found")
    params = parse_defines(defines)
    try:
        return mi.load_file(str(p), **params)
    except RuntimeError as e:
        raise ValueError(f"{p}: {_mitsuba_message(e, p)}") from None


def scene_bbox(scene) -> tuple[np.ndarray, np.ndarray]:
    """The scene's bounding box as (min (3,), max (3,)) float64."""
    b = scene.bbox()
    return np.array(b.min, dtype=np.float64), np.array(b.max, dtype=np.float64)


def load_scene(path: str | os.PathLike, defines=()):
    """:func:`load_file` for fitting: the scene must also have at least one shape and a finite bounding box."""
    p = Path(path)
    scene = load_file(p, defines)
    if not scene.shapes():
        raise ValueError(f"{p}: the scene has no shapes (nothing to fit Gaussians to)")
    lo, hi = scene_bbox(scene)
    if not (scene.bbox().valid() and np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"{p}: the scene's bounding box is empty or infinite")
    return scene


def _named_file(el) -> str | None:
    """The file an XML element names: ``<string name="filename" value=.../>`` or ``<include filename=.../>``."""
    if el.tag == "string" and el.get("name") == "filename":
        return el.get("value")
    if el.tag == "include":
        return el.get("filename")
    return None


def _resolve(name: str, top_folder: Path, xml_folder: Path) -> Path | None:
    """``name`` resolved as Mitsuba's file resolver does: against the top scene's folder first, then against the
    folder of the file that names it; None when neither exists."""
    for base in (top_folder, xml_folder):
        f = (base / name).resolve()
        if f.is_file():
            return f
    return None


def referenced_files(path: str | os.PathLike, defines=()) -> list[Path]:
    """Files a scene file names with ``<string name="filename" .../>`` (and ``<include filename=...>``) that exist,
    recursively through included files; sorted, without duplicates. ``$KEY`` parameters are replaced by ``defines``
    or else the scene's ``<default>`` values, and relative names are resolved as Mitsuba's file resolver does: against
    the top scene's folder first, then against the folder of the file that names them."""
    top = Path(path).resolve()
    params = parse_defines(defines)
    seen: set[Path] = set()

    def substitute(value: str, defaults: dict) -> str:
        return re.sub(r"\$(" + _PARAMETER_NAME + ")",
                      lambda m: params.get(m.group(1), defaults.get(m.group(1), m.group(0))), value)

    def walk(xml: Path):
        try:
            root = ET.parse(xml).getroot()
        except (ET.ParseError, OSError):
            return
        defaults = {el.get("name"): el.get("value", "") for el in root.iter("default")}
        for el in root.iter():
            name = _named_file(el)
            f = _resolve(substitute(name, defaults), top.parent, xml.parent) if name else None
            if f is not None and f not in seen:
                seen.add(f)
                if f.suffix.lower() == ".xml":
                    walk(f)

    walk(top)
    return sorted(seen)
