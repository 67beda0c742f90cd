"""Held-out PSNR curves of run folders, finished or not: a finished run's history.json and metrics.json, an unfinished
one's history from its checkpoint (a run stopped by a time limit still shows how far it got).

    python benchmarks/collect_runs.py /tmp/mi_gs_ablation /tmp/mi_gs_resolution --json runs.json

Every folder below the given roots that holds a config.json and a history (history.json or checkpoints/ckpt.npz) is
one row: iterations done, Gaussians, PSNR at each evaluation listed in --curve, and the final PSNR / SSIM when the run
finished.
"""

from __future__ import annotations

import argparse
import json
import sys
import zipfile
from pathlib import Path

import numpy as np


def read_run(folder: Path) -> dict | None:
    """One run folder's state: {'run', 'finished', 'iteration', 'gaussians', 'curve': {it: psnr}, 'psnr', 'ssim'}."""
    hist, finished, metrics = None, False, {}
    if (folder / "metrics.json").is_file() and (folder / "history.json").is_file():
        hist = json.loads((folder / "history.json").read_text())
        metrics = json.loads((folder / "metrics.json").read_text())
        finished = True
    elif (folder / "checkpoints" / "ckpt.npz").is_file():
        try:
            with np.load(folder / "checkpoints" / "ckpt.npz") as z:
                hist = json.loads(bytes(z["meta"]).decode()).get("history")
        except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as e:
            print(f"{folder}: checkpoint unreadable ({e}), skipped", file=sys.stderr)
            return None
    if not hist or not hist.get("iteration"):
        return None
    curve = {int(i): float(p) for i, p in zip(hist.get("eval_iteration", []), hist.get("test_psnr", []))}
    row = {"run": str(folder), "finished": finished, "iteration": int(hist["iteration"][-1]),
           "gaussians": int(hist["gaussians"][-1]), "seconds": float(hist["seconds"][-1]), "curve": curve}
    test = metrics.get("mean", {})
    for k in ("psnr", "ssim"):
        if isinstance(test.get(k), (int, float)):
            row[k] = float(test[k])
    return row


def collect(roots: list[Path]) -> list[dict]:
    rows = []
    for root in roots:
        for cfg in sorted(Path(root).rglob("config.json")):
            if (row := read_run(cfg.parent)) is not None:
                rows.append(row)
    return rows


def table(rows: list[dict], curve: list[int]) -> str:
    head = ("| run | done | Gaussians | " + " | ".join(f"{c // 1000}k" if c % 1000 == 0 else f"{c:,}" for c in curve)
            + " | final PSNR / SSIM | minutes |")
    lines = [head, "|---|---:|---:|" + "---:|" * len(curve) + "---:|---:|"]
    for r in rows:
        pts = " | ".join(f"{r['curve'][c]:.2f}" if c in r["curve"] else "" for c in curve)
        final = f"{r['psnr']:.2f} / {r['ssim']:.4f}" if "ssim" in r else ""
        lines.append(f"| {r['run']} | {r['iteration']:,}{'' if r['finished'] else ' (stopped)'} | "
                     f"{r['gaussians']:,} | {pts} | {final} | {r['seconds'] / 60:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+", type=Path)
    ap.add_argument("--curve", type=int, nargs="*", default=[2000, 7000, 15000, 30000])
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    rows = collect(args.roots)
    print(table(rows, args.curve))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
