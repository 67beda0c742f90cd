"""A sweep's results: ``results.csv`` (one row per run) and ``results.md`` (the runs, and the mean of each setting
over datasets and seeds), both rewritten atomically as runs finish."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from ..io_utils import atomic_write_text

METRICS = ("psnr", "ssim", "lpips", "gaussians", "training_seconds", "iterations_per_second")


def row(run, status: str, metrics: dict | None = None, resumed_at=None, error: str = "") -> dict:
    """The result row of ``run`` (a ``sweep_spec.PlannedRun``): its metrics (``metrics.json``) when it finished."""
    m = metrics or {}
    mean = m.get("mean", {})
    out = {"run": run.name, "dataset": run.label}
    out.update({k: v for k, v in run.setting})
    out.update({"seed": run.seed, "status": status, "psnr": mean.get("psnr"), "ssim": mean.get("ssim"),
                "lpips": mean.get("lpips"), "gaussians": m.get("gaussians"),
                "training_seconds": m.get("training_seconds"), "iterations_per_second": m.get("iterations_per_second"),
                "resumed_at": resumed_at, "error": error})
    return out


def means(rows: list[dict], grid_keys) -> list[dict]:
    """The mean of every metric per setting (the grid's values), over the finished runs of all datasets and seeds."""
    groups: dict[tuple, tuple[tuple, list[dict]]] = {}
    for r in rows:
        values = tuple(r.get(k) for k in grid_keys)
        groups.setdefault(tuple(map(_hashable, values)), (values, []))[1].append(r)
    out = []
    for values, members in groups.values():
        done = [r for r in members if r["status"] == "done"]
        m = {k: v for k, v in zip(grid_keys, values)}
        m["runs"] = f"{len(done)} of {len(members)}"
        for key in METRICS:
            got = [r[key] for r in done if r.get(key) is not None]
            m[key] = sum(got) / len(got) if got else None
        out.append(m)
    return out


def _hashable(v):
    """``v`` as a key of the groups of :func:`means` (the spec check lets only scalars into a grid; a list, e.g. in
    the rows of an earlier version's sweep, groups by its text rather than failing)."""
    try:
        hash(v)
    except TypeError:
        return repr(v)
    return v


def _shown(key: str, v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if key in ("psnr", "training_seconds"):
        return f"{v:.2f}"
    if key in ("ssim", "lpips"):
        return f"{v:.4f}"
    if key == "gaussians":
        return f"{round(v):,}"
    if key == "iterations_per_second":
        return f"{v:.1f}"
    return str(v)


def _table(rows: list[dict], keys) -> list[str]:
    lines = ["| " + " | ".join(keys) + " |",
             "|" + "|".join("---:" if k in METRICS or k == "resumed_at" else "---" for k in keys) + "|"]
    lines += ["| " + " | ".join(_shown(k, r.get(k)).replace("|", "/") for k in keys) + " |" for r in rows]
    return lines


def write(out: Path, rows: list[dict], grid_keys, title: str) -> None:
    """``out/results.csv`` and ``out/results.md`` of ``rows`` (in the spec's order)."""
    if not rows:
        return
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: ("" if v is None else v) for k, v in r.items()} for r in rows)
    atomic_write_text(Path(out) / "results.csv", text.getvalue())
    shown = [k for k in rows[0] if k != "error"] + (["error"] if any(r["error"] for r in rows) else [])
    lines = [f"# {title}", "", *_table(rows, shown), "", "Mean per setting (finished runs of every dataset and seed):",
             "", *_table(means(rows, grid_keys), [*grid_keys, "runs", *METRICS]), ""]
    atomic_write_text(Path(out) / "results.md", "\n".join(lines))
