"""Typed values of settings: from JSON (a saved ``config.json``) and from command-line text (``--set KEY=VALUE``),
with :class:`SettingError` naming the setting when a value does not fit its type."""

from __future__ import annotations


class SettingError(ValueError):
    """A setting with a wrong name, type or value: ``key`` is its ``section.field`` name."""

    def __init__(self, key: str, problem: str):
        self.key, self.problem = key, problem
        super().__init__(f"setting {key!r}: {problem}")


def json_value(kind, v, key: str):
    """A JSON value ``v`` as the type ``kind`` (bool, int, float, str, tuples of those, optionally ``| None``)."""
    import math
    import types
    import typing

    args = typing.get_args(kind)
    if isinstance(kind, types.UnionType) or typing.get_origin(kind) is typing.Union:
        if v is None and type(None) in args:
            return None
        (kind,) = [a for a in args if a is not type(None)]
        args = typing.get_args(kind)
    if typing.get_origin(kind) is tuple:
        if not isinstance(v, (list, tuple)):
            raise SettingError(key, f"expected a list, got {shown(v)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(json_value(args[0], x, key) for x in v)
        if len(v) != len(args):
            raise SettingError(key, f"expected a list of {len(args)} values, got {shown(v)}")
        return tuple(json_value(a, x, key) for a, x in zip(args, v))
    if kind is bool and isinstance(v, bool):
        return v
    if kind is int and isinstance(v, int) and not isinstance(v, bool):
        return v
    if kind is float and isinstance(v, (int, float)) and not isinstance(v, bool):
        if not math.isfinite(v):
            raise SettingError(key, f"expected a finite number, got {v}")
        return float(v)
    if kind is str and isinstance(v, str):
        return v
    what = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(kind, str(kind))
    raise SettingError(key, f"expected {what}, got {shown(v)}")


def shown(v) -> str:
    import json

    text = json.dumps(v) if isinstance(v, (dict, list, str, int, float, bool, type(None))) else repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


def parse_value(kind, text: str, key: str):
    """``text`` as a value of the type ``kind`` (bool, int, float, str, tuples of those, optionally ``| None``)."""
    import types
    import typing

    args = typing.get_args(kind)
    if isinstance(kind, types.UnionType) or typing.get_origin(kind) is typing.Union:
        if text.lower() == "none" and type(None) in args:
            return None
        (kind,) = [a for a in args if a is not type(None)]
        args = typing.get_args(kind)
    if typing.get_origin(kind) is tuple:
        items = [t for t in text.replace(",", " ").split() if t]
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(parse_value(args[0], t, key) for t in items)
        if len(items) != len(args):
            raise SettingError(key, f"expected {len(args)} comma-separated values, got {text!r}")
        return tuple(parse_value(a, t, key) for a, t in zip(args, items))
    try:
        if kind is bool:
            low = text.lower()
            if low not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return low in ("true", "1", "yes")
        if kind is int:
            return int(text.replace("_", ""))
        if kind is float:
            value = float(text)
            if value != value or value in (float("inf"), float("-inf")):
                raise ValueError
            return value
        if kind is str:
            return text
    except ValueError:
        raise SettingError(key, f"{text!r} is not a valid {kind.__name__}") from None
    raise SettingError(key, f"values of type {kind} cannot be set from the command line")
