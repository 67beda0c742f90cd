"""Ours against gsplat's recipe test view by test view, from a `gpu_check.sh quality` folder: our runs' metrics.json
(``ROOT/ablation/<dataset>/<setup>_<iterations>of<schedule>/``) beside ``ROOT/gsplat_<peer>.json`` (written by
``benchmarks/gsplat_train.py --out``, which keeps per-view scores). With a handful of test views one view can move
a mean by a dB (fox: 7 views), so a comparison that ranks two trainers looks at the views first.

    python benchmarks/compare_views.py /tmp/q
    python benchmarks/compare_views.py /tmp/q --setup no_reset
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# our dataset name (benchmarks/ablation.py) -> gsplat_train.py's (benchmarks/train.py), as gpu_check.sh pairs them
PEERS = {"mi_room_colmap": "mi_room_colmap", "fox_r4": "fox", "maryrose_r8": "maryrose",
         "mi_objects_colmap": "mi_objects_colmap"}


def views_table(root: Path, setup: str = "defaults") -> list[str]:
    """Markdown lines: per dataset, each test view's PSNR for ours and gsplat's recipe, and the difference."""
    lines = []
    for ours_name, peer in PEERS.items():
        runs = sorted((root / "ablation" / ours_name).glob(f"{setup}_*of*/metrics.json"))
        peer_file = root / f"gsplat_{peer}.json"
        if not runs or not peer_file.is_file():
            continue
        ours = json.loads(runs[-1].read_text())
        rows = json.loads(peer_file.read_text())
        theirs = next((r for r in reversed(rows) if r.get("iterations") == ours.get("iterations")), rows[-1])
        if "views" not in theirs:
            lines.append(f"{ours_name}: {peer_file} has no per-view scores (written by an older gsplat_train.py)")
            continue
        lines += [f"\n{ours_name} ({runs[-1].parent.name}) against gsplat's recipe ({peer}), "
                  f"{ours.get('iterations', '?')} iterations", "| view | ours PSNR | gsplat PSNR | ours - gsplat |",
                  "|---|---:|---:|---:|"]
        for name, s in ours["views"].items():
            g = theirs["views"].get(name)
            if g is None:
                lines.append(f"| {name} | {s['psnr']:.2f} | - | - |")
            else:
                lines.append(f"| {name} | {s['psnr']:.2f} | {g['psnr']:.2f} | {s['psnr'] - g['psnr']:+.2f} |")
        lines.append(f"| mean | {ours['mean']['psnr']:.2f} | {theirs['psnr']:.2f} | "
                     f"{ours['mean']['psnr'] - theirs['psnr']:+.2f} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="the quality folder (gpu_check.sh's Q_ROOT, /tmp/q by default)")
    ap.add_argument("--setup", default="defaults", help="our ablation setup to compare (default: defaults)")
    args = ap.parse_args(argv)
    lines = views_table(args.root, args.setup)
    if not lines:
        print(f"compare_views.py: {args.root}: no pair of our run and gsplat's JSON found", file=sys.stderr)
        return 2
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
