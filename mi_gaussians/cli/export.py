"""``mi-gs export MODEL -o OUT``: a model (.ply, .splat, .spz, .glb or .gltf) written in another of these formats,
optionally with fewer SH bands."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from .args import add_model_input, add_output, is_model, model_suffixes, sh_degree
from .errors import InputError, warn


def add_parser(sub) -> None:
    s = sub.add_parser("export", help="write a model as .splat (32 bytes per Gaussian, web viewers), .spz (Niantic's "
                                      "compressed format), .glb / .gltf (glTF 2.0, KHR_gaussian_splatting) or .ply")
    add_model_input(s, "model.ply, .splat, .spz, .glb or .gltf",
                    antialiased="record in an .spz that the model renders anti-aliased (default: as the run whose "
                                "config.json sits beside the model was trained)")
    add_output(s, "out.splat, out.spz, out.glb, out.gltf or out.ply", overwrite="replace an existing output file")
    s.add_argument("--sh-degree", type=sh_degree, default=None,
                   help="keep the SH bands up to this degree (default: all the model has; .splat keeps degree 0)")
    s.add_argument("--spz-version", type=int, choices=(3, 4), default=4,
                   help=".spz version to write: 4 (zstd streams, the reference library's and splat-transform's "
                        "default) or 3 (one gzip stream, for older readers)")
    s.add_argument("--color-space", choices=("srgb", "linear"), default=None,
                   help="what the model's colours are, recorded in a .glb/.gltf (default: as a glTF input says, else "
                        "as the dataset of the run whose config.json sits beside the model, else srgb)")


def _color_space(src: Path, meta: dict, record_warned: bool) -> str:
    """The model's colour space: a glTF input's, else that of the dataset its run (config.json beside it) trained
    on, else sRGB (models trained on photos). ``record_warned``: the run's record was found unreadable and said so
    already."""
    if "color_space" in meta:
        return meta["color_space"]
    from ..run_folder import CONFIG, RunRecord

    if not (src.parent / CONFIG).is_file():
        return "srgb"
    from ..runs import run_dataset

    why = "give --color-space to say otherwise"
    try:
        record = RunRecord.read(src.parent, "")
    except ValueError as e:
        if not record_warned:
            warn(f"writing the colours as sRGB ({why}): {e}")
        return "srgb"
    try:
        return run_dataset(record, src.parent, render_missing=False, progress=False, log=None).color_space
    except (ValueError, OSError, RuntimeError) as e:
        warn(f"writing the colours as sRGB ({why}): the run's dataset cannot be read ({e})")
        return "srgb"


def run(args) -> int:
    from ..io_utils import check_output_file, remove_stale_temporary_files
    from ..model.web_formats import drop_sh_bands, read_model_info, write_model
    from ..runs import model_raster_config

    src, out = Path(args.input), Path(args.output)
    names = ", ".join(model_suffixes())
    if not src.is_file():
        raise InputError(f"{src}: not found")
    if not is_model(src):
        raise InputError(f"{src}: expected a model ({names})")
    if not is_model(out):
        raise InputError(f"{out}: unknown output format {out.suffix or '(none)'} (use {names})")
    check_output_file(out)
    if out.exists() and not args.overwrite:
        raise InputError(f"{out}: exists (give --overwrite to replace it)")
    if out.exists() and out.resolve() == src.resolve():
        raise InputError(f"{out}: is the input model")
    params, meta = read_model_info(src)
    if len(params["means"]) == 0:
        raise InputError(f"{src}: the model has no Gaussians (nothing to export)")
    remove_stale_temporary_files(out.parent if str(out.parent) else ".")
    if args.sh_degree is not None:
        params = drop_sh_bands(params, args.sh_degree)
    kind = out.suffix.lower()
    if kind == ".splat" and params["sh_rest"].shape[1]:
        print(f"mi-gs: note: .splat holds SH degree 0 only; the higher bands of {src} are dropped", file=sys.stderr)
    warned = []

    def record_warning(line: str) -> None:
        warned.append(line)
        warn(line)

    antialiased = model_raster_config(src, args.antialiased, warn=record_warning).antialiased
    if antialiased and kind != ".spz":
        print(f"mi-gs: note: {out.suffix} cannot record that {src} renders anti-aliased: render it with "
              "--antialiased", file=sys.stderr)
    color_space = args.color_space or (_color_space(src, meta, bool(warned)) if kind in (".glb", ".gltf") else "srgb")
    if meta.get("color_space") == "linear" and kind not in (".glb", ".gltf"):
        print(f"mi-gs: note: {out.suffix} cannot record that the colours of {src} are linear: render it with "
              "--color-space linear", file=sys.stderr)
    write_model(out, params, antialiased=antialiased, spz_version=args.spz_version, color_space=color_space)
    size, before = os.path.getsize(out), os.path.getsize(src)
    report = {"output": str(out), "gaussians": int(len(params["means"])), "bytes": size,
              "bytes_per_gaussian": round(size / len(params["means"]), 2), "size_ratio": round(before / size, 2)}
    if kind == ".spz":
        report["spz_version"] = args.spz_version
    if kind in (".glb", ".gltf"):
        report["color_space"] = color_space
    print(json.dumps(report, indent=2))
    return 0
