"""``mi-gs export MODEL -o OUT``: a model (.ply, .splat or .spz) written in another of these formats, optionally
with fewer SH bands."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from .args import add_model_input, add_output, is_model, sh_degree
from .errors import InputError, warn


def add_parser(sub) -> None:
    s = sub.add_parser("export", help="write a model as .splat (32 bytes per Gaussian, web viewers), .spz (Niantic's "
                                      "compressed format) or .ply")
    add_model_input(s, "model.ply, .splat or .spz",
                    antialiased="record in an .spz that the model renders anti-aliased (default: as the run whose "
                                "config.json sits beside the model was trained)")
    add_output(s, "out.splat, out.spz or out.ply", overwrite="replace an existing output file")
    s.add_argument("--sh-degree", type=sh_degree, default=None,
                   help="keep the SH bands up to this degree (default: all the model has; .splat keeps degree 0)")


def run(args) -> int:
    from ..io_utils import check_output_file, remove_stale_temporary_files
    from ..model.web_formats import drop_sh_bands, read_model, write_model
    from ..runs import model_raster_config

    src, out = Path(args.input), Path(args.output)
    if not src.is_file():
        raise InputError(f"{src}: not found")
    if not is_model(src):
        raise InputError(f"{src}: expected a model (.ply, .splat or .spz)")
    if not is_model(out):
        raise InputError(f"{out}: unknown output format {out.suffix or '(none)'} (use .ply, .splat or .spz)")
    check_output_file(out)
    if out.exists() and not args.overwrite:
        raise InputError(f"{out}: exists (give --overwrite to replace it)")
    if out.exists() and out.resolve() == src.resolve():
        raise InputError(f"{out}: is the input model")
    params, _ = read_model(src)
    if len(params["means"]) == 0:
        raise InputError(f"{src}: the model has no Gaussians (nothing to export)")
    remove_stale_temporary_files(out.parent if str(out.parent) else ".")
    if args.sh_degree is not None:
        params = drop_sh_bands(params, args.sh_degree)
    if out.suffix.lower() == ".splat" and params["sh_rest"].shape[1]:
        print(f"mi-gs: note: .splat holds SH degree 0 only; the higher bands of {src} are dropped", file=sys.stderr)
    antialiased = model_raster_config(src, args.antialiased, warn=warn).antialiased
    if antialiased and out.suffix.lower() != ".spz":
        print(f"mi-gs: note: {out.suffix} cannot record that {src} renders anti-aliased: render it with "
              "--antialiased", file=sys.stderr)
    write_model(out, params, antialiased=antialiased)
    size, before = os.path.getsize(out), os.path.getsize(src)
    print(json.dumps({"output": str(out), "gaussians": int(len(params["means"])), "bytes": size,
                      "bytes_per_gaussian": round(size / len(params["means"]), 2),
                      "size_ratio": round(before / size, 2)}, indent=2))
    return 0
