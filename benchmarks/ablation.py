"""Densification rules one at a time: each rule on and off on the shared datasets, at 7k iterations of the 30k
schedule (the comparison gsplat's recipe is measured on) or any other length, through the command line.

    python benchmarks/ablation.py mi_objects_colmap                          # every setup, 7k of the 30k schedule
    python benchmarks/ablation.py mi_objects_colmap mi_room_colmap --only defaults reference
    python benchmarks/ablation.py fox maryrose --iterations 7000 --schedule 30000
    python benchmarks/ablation.py mi_objects_colmap --only defaults --iterations 30000   # a whole run

Each setup is a list of ``--set`` options on top of the defaults of the checkout that runs it (``defaults``: none).
Runs are kept in --out (default /tmp/mi_gs_ablation/<dataset>/<setup>_<iterations>of<schedule>) and reused; an
interrupted one resumes. The table gives held-out PSNR at every 1000 iterations listed in --curve (from the run's
history), the final PSNR / SSIM, Gaussians and training minutes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from cli_run import train  # noqa: E402

DATA = (ROOT / ".." / "shared" / "data").resolve()

# dataset -> (folder under ../shared/data, optimize options); the real captures at the coarser -r of the README's
# strategy table, so that a rule can be tried on all four within a working day of the 2-core VM
DATASETS = {
    "mi_objects_colmap": ("mi_objects/colmap", ["--white-background"]),
    "mi_objects_colmap_r2": ("mi_objects/colmap", ["-r", "2", "--white-background"]),   # 100x100: 30k runs affordable
    "mi_room_colmap": ("mi_room/colmap", []),
    "mi_room_colmap_r2": ("mi_room/colmap", ["-r", "2"]),     # 128x128
    "fox": ("fox", ["-r", "8"]),
    "fox_r4": ("fox", ["-r", "4"]),
    "maryrose": ("maryrose", ["-r", "16", "--white-background"]),
    "maryrose_r8": ("maryrose", ["-r", "8", "--white-background"]),
}

# setup -> --set assignments. "defaults": the checkout's own; "reference": the 2023 reference's effective rules
# (opacity resets every 3000 and at 500 on a white background, no screen-size prune: its 20 px test never fires),
# spelled out so that a run folder keeps its meaning when the defaults change; every other setup is "reference" with
# one rule changed ("screen_0.1" is what mi-gs did before on a 200-pixel image: 20 px).
REFERENCE = ["densify.opacity_reset_interval=3000", "densify.max_screen_fraction=0", "optim.ssim_padding=same",
             "optim.step_on_refine=false", "raster.near_plane=0.2", "raster.alpha_max=0.99", "data.extent=cameras"]
CHANGES = {
    "screen_0.1": ["densify.max_screen_fraction=0.1"],
    "screen_0.15": ["densify.max_screen_fraction=0.15"],
    "no_reset": ["densify.opacity_reset_interval=0"],
    "reset_once": ["densify.reset_once=true"],
    "ssim_valid": ["optim.ssim_padding=valid"],
    "step_on_refine": ["optim.step_on_refine=true"],
    "near_0.01": ["raster.near_plane=0.01"],
    "alpha_0.999": ["raster.alpha_max=0.999"],
    "no_world_prune": ["densify.max_world_scale=1000"],
    "scene_extent": ["data.extent=scene"],
    "scene_extent_no_world_prune": ["data.extent=scene", "densify.max_world_scale=1000"],
    "depth_extent": ["data.extent=depth"],
    "depth_extent_no_world_prune": ["data.extent=depth", "densify.max_world_scale=1000"],
}
# gsplat 1.5.3's simple_trainer as it runs: every rule above where it differs from the reference
CHANGES["gsplat"] = [*CHANGES["no_reset"], *CHANGES["ssim_valid"], *CHANGES["step_on_refine"], *CHANGES["near_0.01"],
                     *CHANGES["alpha_0.999"]]
SETUPS = {"defaults": [], "size_classes": ["row_classes=4"],    # (the defaults, frozen steps padded to size classes)
          "reference": REFERENCE,
          **{name: [*REFERENCE, *change] for name, change in CHANGES.items()},
          # one rule changed on top of the checkout's own defaults (not the reference's)
          **{f"defaults+{name}": change for name, change in CHANGES.items()}}


def run(name: str, setup: str, iterations: int, schedule: int, out_root: Path) -> dict | None:
    folder, extra = DATASETS[name]
    src = DATA / folder
    if not src.is_dir():
        print(f"{name}: {src} not found, skipped", file=sys.stderr)
        return None
    options = [*extra, "--eval-every", "1000", "--set", f"optim.position_lr_max_steps={schedule}",
               "--set", f"densify.densify_until_iter={min(15000, schedule // 2)}"]
    for s in SETUPS[setup]:
        options += ["--set", s]
    out = out_root / name / f"{setup}_{iterations}of{schedule}"
    m = train(src, out, iterations, options)
    h = json.loads((out / "history.json").read_text())
    curve = dict(zip(h["eval_iteration"], h["test_psnr"]))
    return {"dataset": name, "setup": setup, "psnr": m["mean"]["psnr"], "ssim": m["mean"]["ssim"],
            "gaussians": m["gaussians"], "minutes": m["training_seconds"] / 60, "curve": curve}


def curve_text(curve: dict, at: list[int]) -> str:
    """A run's held-out PSNR at the iterations ``at`` ("-" where its curve has no evaluation)."""
    return " / ".join(f"{curve[c]:.2f}" if c in curve else "-" for c in at)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("datasets", nargs="+", choices=sorted(DATASETS))
    ap.add_argument("--only", nargs="+", choices=sorted(SETUPS), default=list(SETUPS))
    ap.add_argument("--iterations", type=int, default=7000)
    ap.add_argument("--schedule", type=int, default=30000, help="the run whose schedules are used (>= --iterations)")
    ap.add_argument("--curve", type=int, nargs="*", default=[2000, 4000], help="also show PSNR at these iterations")
    ap.add_argument("--out", default="/tmp/mi_gs_ablation")
    args = ap.parse_args(argv)
    schedule = max(args.schedule, args.iterations)
    rows = [r for name in args.datasets for setup in args.only
            if (r := run(name, setup, args.iterations, schedule, Path(args.out))) is not None]
    at = " / ".join(f"{c // 1000}k" for c in args.curve)
    print(f"\n{args.iterations} iterations of the {schedule} schedule; held-out PSNR (at {at}), final PSNR / SSIM\n")
    print(f"| dataset | setup | options | PSNR {at} | PSNR | SSIM | Gaussians | minutes |")
    print("|---|---|---|---|---:|---:|---:|---:|")
    for r in rows:
        curve = curve_text(r["curve"], args.curve)
        opts = " ".join(f"`{s}`" for s in CHANGES.get(r["setup"].removeprefix("defaults+"), [])) or "-"
        print(f"| {r['dataset']} | {r['setup']} | {opts} | {curve} | {r['psnr']:.2f} | {r['ssim']:.4f} "
              f"| {r['gaussians']:,} | {r['minutes']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
