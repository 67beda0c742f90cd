"""The spec of a sweep (``mi-gs sweep SPEC.toml``): datasets x every combination of the grid's settings x seeds, each
one run. Read and checked whole before anything starts: a bad spec is one line naming the file and the key.

    datasets = ["../shared/data/mi_objects/colmap", "scenes/objects.xml"]   # folders, scene files, or globs
    iterations = 3000                    # optional (default: the paper's 30k), with its proportions
    seeds = [0, 1]                       # optional, default [0]
    retries = 3                          # optional: how often Ray runs a task again whose worker died
    [set]                                # fixed settings of every run (as --set SECTION.FIELD=VALUE)
    "data.resolution" = 2
    [grid]                               # every combination of these settings' values
    strategy = ["default", "mcmc"]
    [resources]                          # per run: default 1 CPU, and 1 GPU on the CUDA variants
    cpus = 1

Relative paths are relative to the spec's folder. A run's folder is ``runs/<dataset>-<setting>-s<seed>``, the setting
being the grid's values joined by ``_`` (no part for an empty grid).
"""

from __future__ import annotations

import glob
import itertools
import re
from dataclasses import dataclass
from pathlib import Path

from ..config import SettingError, TrainConfig
from ..data.dataset import detect_layout
from ..data.scene_file import is_scene_file

KEYS = ("datasets", "iterations", "seeds", "retries", "set", "grid", "resources")
#: settings a sweep gives every run itself, from its own keys: in [set] or [grid] they would be dropped or mixed
SWEEP_OWNED = {
    "seed": "a run's seed comes from the spec's seeds = [...] (give the seeds there)",
    "data.seed": "a run's seed comes from the spec's seeds = [...] (give the seeds there)",
    "optim.iterations": "give the number of iterations as the spec's iterations = N, which also scales the schedule "
                        "(densification, learning rates) as mi-gs optimize --iterations does",
}
RESOURCES = ("cpus", "gpus")


@dataclass(frozen=True)
class PlannedRun:
    """One run of a sweep."""

    name: str                    # its folder's name under OUT/runs
    dataset: Path                # the dataset folder or scene file (absolute)
    label: str                   # the dataset's short name (in the folder name and the results)
    setting: tuple               # ((key, value), ...) of the grid, in the grid's order
    seed: int
    config: TrainConfig

    @property
    def scene_file(self) -> bool:
        return is_scene_file(self.dataset)


@dataclass(frozen=True)
class SweepSpec:
    path: Path
    datasets: tuple[Path, ...]
    labels: tuple[str, ...]
    iterations: int | None
    seeds: tuple[int, ...]
    settings: tuple[tuple[str, object], ...]
    grid: tuple[tuple[str, tuple], ...]
    cpus: float
    gpus: float
    retries: int
    runs: tuple[PlannedRun, ...]
    notes: tuple[str, ...] = ()      # what in the spec has no effect (a grid of one value, a setting no run uses)

    @property
    def grid_keys(self) -> tuple[str, ...]:
        return tuple(k for k, _ in self.grid)


def read_spec(path: str | Path, cuda: bool = False) -> SweepSpec:
    """The sweep in the TOML file ``path`` (``cuda``: runs take a GPU by default); ValueError with one line naming
    the file and the key when anything in it is wrong, including every run's settings."""
    import tomllib

    path = Path(path)
    try:
        with open(path, "rb") as f:
            spec = tomllib.load(f)
    except FileNotFoundError:
        raise ValueError(f"{path}: sweep spec not found") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: is a folder, not a sweep spec (.toml)") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: not valid TOML ({e})") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text (a TOML file is UTF-8; byte {e.start} is not)") from None

    def bad(key: str, problem: str) -> ValueError:
        return ValueError(f"{path}: {key}: {problem}")

    unknown = sorted(set(spec) - set(KEYS))
    if unknown:
        raise bad(unknown[0], f"not a key of a sweep spec (keys: {', '.join(KEYS)})")
    datasets = _datasets(spec.get("datasets"), path.parent.resolve(), bad)
    labels = _labels(datasets, bad)
    iterations = spec.get("iterations")
    if iterations is not None and (not _is_int(iterations) or iterations < 1):
        raise bad("iterations", f"expected a positive integer, got {iterations!r}")
    seeds = spec.get("seeds", [0])
    if (not isinstance(seeds, list) or not seeds or not all(_is_int(s) and s >= 0 for s in seeds)
            or len(set(seeds)) != len(seeds)):
        raise bad("seeds", f"expected a list of different integers >= 0, got {seeds!r}")
    retries = spec.get("retries", 3)
    if not _is_int(retries) or retries < 0:
        raise bad("retries", f"expected an integer >= 0, got {retries!r}")
    settings = _table(spec, "set", bad)
    grid = _table(spec, "grid", bad)
    notes = []
    for key, values in grid:
        if not isinstance(values, list) or not values:
            raise bad(f"grid.{key}", f"expected a non-empty list of values, got {values!r}")
        for v in values:
            if not isinstance(v, (bool, int, float, str)):
                raise bad(f"grid.{key}", f"each value must be one number, string or true/false, got {v!r} (a setting "
                                         'of several numbers takes them as one string: "1,1,1")')
        if len(set(map(_text, values))) != len(values):
            raise bad(f"grid.{key}", f"values repeat: {values!r}")
        if len(values) == 1:
            notes.append(f"{path}: grid.{key} has one value ({_text(values[0])}): every run has it, as [set] would "
                         "give it; give two or more values to compare them")
    for key, _ in settings:
        if key in dict(grid):
            raise bad(f"set.{key}", "is also in [grid] (give it in one of them)")
    for table, items in (("set", settings), ("grid", grid)):
        for key, _ in items:
            if key in SWEEP_OWNED:
                raise bad(f"{table}.{key}", SWEEP_OWNED[key])
    resources = dict(_table(spec, "resources", bad))
    for key in resources:
        if key not in RESOURCES:
            raise bad(f"resources.{key}", f"not a resource of a run (resources: {', '.join(RESOURCES)})")
    cpus, gpus = resources.get("cpus", 1), resources.get("gpus", 1 if cuda else 0)
    for key, value, zero in (("cpus", cpus, False), ("gpus", gpus, True)):
        if problem := _resource_problem(value, zero):
            raise bad(f"resources.{key}", f"{problem}, got {value!r}")
    runs, inert = _plan(path, datasets, labels, iterations, seeds, settings, grid)
    return SweepSpec(path, datasets, labels, iterations, tuple(seeds), settings,
                     tuple((k, tuple(v)) for k, v in grid), float(cpus), float(gpus), int(retries), runs,
                     tuple(notes + inert))


def _resource_problem(value, zero: bool) -> str | None:
    """Why ``value`` is no amount of a Ray resource per run (None when it is one): Ray takes a whole number, or a
    fraction of one in steps of 0.0001 (``zero``: 0 too)."""
    import math

    what = f"expected a whole number {'>= 0' if zero else '>= 1'}, or a fraction between 0 and 1 in steps of 0.0001"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return what
    if value == 0:
        return None if zero else what
    if value < 0 or (value > 1 and value != int(value)) or (value < 1 and abs(value * 1e4 - round(value * 1e4)) > 1e-6):
        return what
    return None if value >= 1e-4 else what


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _text(value) -> str:
    """A TOML value as the text of ``--set KEY=TEXT``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return ",".join(_text(v) for v in value)
    return str(value)


def _table(spec: dict, name: str, bad) -> tuple[tuple[str, object], ...]:
    table = spec.get(name, {})
    if not isinstance(table, dict):
        raise bad(name, f"expected a table ([{name}]), got {table!r}")
    out = []
    for key, value in table.items():                 # ("data.resolution" = 2, or [set.data] resolution = 2)
        if isinstance(value, dict) and name != "resources":
            out += [(f"{key}.{k}", v) for k, v in value.items()]
        else:
            out.append((key, value))
    return tuple(out)


def _datasets(entries, root: Path, bad) -> tuple[Path, ...]:
    if not isinstance(entries, list) or not entries or not all(isinstance(e, str) and e for e in entries):
        raise bad("datasets", f"expected a non-empty list of folders, scene files or globs, got {entries!r}")
    out = []
    for i, entry in enumerate(entries):
        pattern = entry if Path(entry).is_absolute() else str(root / entry)
        found = sorted(glob.glob(pattern)) if glob.has_magic(entry) else [pattern]
        if not found:
            raise bad(f"datasets[{i}]", f"{entry!r} matches nothing")
        for p in map(Path, found):
            if not p.exists():
                raise bad(f"datasets[{i}]", f"{p}: not found")
            if not (p.is_dir() or is_scene_file(p)):
                raise bad(f"datasets[{i}]", f"{p}: neither a dataset folder nor a Mitsuba scene file (.xml)")
            if p.is_dir():
                try:
                    detect_layout(p)
                except ValueError as e:
                    raise bad(f"datasets[{i}]", str(e)) from None
            if p.resolve() not in out:
                out.append(p.resolve())
    return tuple(out)


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._+=-]+", "-", text).strip("-") or "x"


def _labels(datasets, bad) -> tuple[str, ...]:
    """Short names: the folder's name or the scene's stem, with its parent's name where two are alike."""
    names = [_safe(p.stem if is_scene_file(p) else p.name) for p in datasets]
    names = [f"{_safe(p.parent.name)}_{n}" if names.count(n) > 1 else n for p, n in zip(datasets, names)]
    for i, n in enumerate(names):
        if names.count(n) > 1:
            raise bad(f"datasets[{i}]", f"two datasets would share the run name {n!r}; give folders with "
                                        "different names")
    return tuple(names)


def _plan(path, datasets, labels, iterations, seeds, settings, grid) -> tuple[tuple[PlannedRun, ...], list[str]]:
    """The runs, and a note for each setting of the spec that has no effect in some of them
    (:func:`mi_gaussians.setting_effects.inert`)."""
    from ..setting_effects import inert

    keys = [k for k, _ in grid]
    runs, names = [], set()
    unused: dict[str, tuple[int, str]] = {}       # "set.KEY" / "grid.KEY" -> (runs where it has no effect, why)
    for (dataset, label), values, seed in itertools.product(zip(datasets, labels),
                                                            itertools.product(*[v for _, v in grid]), seeds):
        setting = tuple(zip(keys, values))
        texts = [(f"set.{k}", f"{k}={_text(v)}") for k, v in settings]
        texts += [(f"grid.{k}", f"{k}={_text(v)}") for k, v in setting]
        cfg = TrainConfig() if iterations is None else TrainConfig().with_iterations(iterations)
        where = {text.partition("=")[0]: origin for origin, text in texts}
        try:
            cfg = cfg.with_settings([t for _, t in texts] + [f"seed={seed}", f"data.seed={seed}"])
            cfg = cfg.check(is_scene_file(dataset), given=list(where))
        except SettingError as e:
            setting_text = ", ".join(f"{k}={_text(v)}" for k, v in setting) or "every run"
            raise ValueError(f"{path}: {where.get(e.key, e.key)}: {e.problem} (the runs with {setting_text})") \
                from None
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
        for key, why in inert(cfg, [k for k in where if k not in ("seed", "data.seed")], is_scene_file(dataset)):
            count, first = unused.get(where[key], (0, why))
            unused[where[key]] = (count + 1, first)
        name = "-".join([label] + (["_".join(_safe(_text(v)) for v in values)] if keys else []) + [f"s{seed}"])
        if name in names:
            raise ValueError(f"{path}: grid: two runs would share the folder name {name!r} (values that differ only "
                             "in characters a folder name cannot hold)")
        names.add(name)
        runs.append(PlannedRun(name, dataset, label, setting, seed, cfg))
    notes = []
    for origin, (count, why) in unused.items():
        which = ("the sweep's one run" if len(runs) == 1 else f"all {count} runs" if count == len(runs)
                 else f"{count} of the {len(runs)} runs")
        notes.append(f"{path}: {origin} has no effect in {which}: {why}")
    return tuple(runs), notes
