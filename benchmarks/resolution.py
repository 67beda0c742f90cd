"""Training quality against image size: the same scene trained at several image sizes, held-out PSNR at 2k / 4k /
7k (by default 7k iterations of the 30k schedule, the comparison gsplat's recipe is measured on). A rule of the
trainer stated in pixels shows up here as a larger image scoring below a smaller one.

    python benchmarks/resolution.py objects --sizes 200 400                 # scenes/objects.xml path-traced at each
    python benchmarks/resolution.py maryrose --sizes 16 8                   # a dataset at -r 16 and -r 8
    python benchmarks/resolution.py fox --sizes 4 2 --iterations 4000
    python benchmarks/resolution.py objects --sizes 200 400 --code /tmp/before --tag before   # an earlier checkout

A name of ``scenes/<name>.xml`` is path-traced by ``mi-gs optimize`` at each film size (``-r S``: S x S pixels, the
references cached in --out/<name>/references and shared by every run); a dataset of ``ablation.DATASETS``' folders
is read at ``-r S``. Runs go through the command line, are kept in --out and reused; ``--set`` adds settings to
every run, ``--code`` runs another checkout (a ``git worktree`` of an earlier commit).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from ablation import DATA, DATASETS, curve_text  # noqa: E402
from cli_run import train  # noqa: E402


def source(name: str) -> tuple[Path, list[str], bool]:
    """(path, options, is a scene file) of a benchmark name."""
    xml = ROOT / "scenes" / f"{name}.xml"
    if xml.is_file():
        return xml, [], True
    folder, options = DATASETS[name]
    options = list(options)
    if "-r" in options:                                 # the size is given per run
        i = options.index("-r")
        del options[i:i + 2]
    return DATA / folder, options, False


def run(name: str, size: int, iterations: int, schedule: int, settings: list[str], out_root: Path,
        code: Path | None, tag: str) -> dict | None:
    src, options, scene = source(name)
    if not src.exists():
        print(f"{name}: {src} not found, skipped", file=sys.stderr)
        return None
    options = [*options, "-r", str(size), "--eval-every", "1000",
               "--set", f"optim.position_lr_max_steps={schedule}",
               "--set", f"densify.densify_until_iter={min(15000, schedule // 2)}"]
    if scene:
        options += ["--cache", str(out_root / name / "references")]
    for s in settings:
        options += ["--set", s]
    out = out_root / name / f"{tag}_r{size}_{iterations}of{schedule}"
    m = train(src, out, iterations, options, code)
    h = json.loads((out / "history.json").read_text())
    return {"name": name, "size": size, "tag": tag, "psnr": m["mean"]["psnr"], "ssim": m["mean"]["ssim"],
            "gaussians": m["gaussians"], "minutes": m["training_seconds"] / 60,
            "curve": dict(zip(h["eval_iteration"], h["test_psnr"]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("name", help="a scenes/<name>.xml, or a dataset of benchmarks/ablation.py")
    ap.add_argument("--sizes", type=int, nargs="+", required=True,
                    help="film sizes in pixels (scene file), or -r divisors (dataset)")
    ap.add_argument("--iterations", type=int, default=7000)
    ap.add_argument("--schedule", type=int, default=30000)
    ap.add_argument("--curve", type=int, nargs="*", default=[2000, 4000])
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    ap.add_argument("--code", type=Path, default=None, help="run this checkout instead of the installed one")
    ap.add_argument("--tag", default="current", help="names the runs (e.g. before / after)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/mi_gs_resolution"))
    args = ap.parse_args(argv)
    schedule = max(args.schedule, args.iterations)
    rows = [r for size in args.sizes if (r := run(args.name, size, args.iterations, schedule, args.settings,
                                                   args.out, args.code, args.tag)) is not None]
    at = " / ".join(f"{c // 1000}k" for c in args.curve)
    print(f"\n{args.iterations} iterations of the {schedule} schedule; held-out PSNR at {at} and at the end\n")
    print(f"| scene | size | code | PSNR {at} | PSNR | SSIM | Gaussians | minutes |")
    print("|---|---|---|---|---:|---:|---:|---:|")
    for r in rows:
        curve = curve_text(r["curve"], args.curve)
        size = f"{r['size']} px" if source(r["name"])[2] else f"-r {r['size']}"
        print(f"| {r['name']} | {size} | {r['tag']} | {curve} | {r['psnr']:.2f} | {r['ssim']:.4f} "
              f"| {r['gaussians']:,} | {r['minutes']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
