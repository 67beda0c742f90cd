"""What the commands share: argument types (each refuses a bad value in one line), the flag groups several commands
take (the Mitsuba variant, the output and ``--overwrite``, a model input, scene parameters, the viewer), and the
checks behind them."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from .errors import InputError

# The rasterizer is Dr.Jit code with a hand-written backward pass and RGB colours: a JIT variant with automatic
# differentiation and RGB colour
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
VARIANT_HELP = "Mitsuba variant: llvm_ad_rgb or cuda_ad_rgb (default: cuda_ad_rgb if a GPU is available)"


# ------------------------------------------------------------------------------------------------ argument types
def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def port_number(text: str) -> int:
    """argparse type: a TCP port, 1..65535."""
    value = _integer(text)
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port number from 1 to 65535, got {text}")
    return value


def sized(low: int, high: int, what: str):
    """argparse type: an integer from ``low`` to ``high`` (``what``: where the bounds come from)."""

    def parse(text: str) -> int:
        value = _integer(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected {low} to {high} pixels ({what}), got {text}")
        return value

    return parse


def output_path(text: str) -> str:
    """argparse type: a path that is not empty (``-o ''``, an unset shell variable, would write into the current
    folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty one (an unset shell variable?)")
    return text


def finite_float(text: str) -> float:
    """argparse type: a finite number (no nan or inf)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text}")
    return value


def field_of_view(text: str) -> float:
    """argparse type: a field of view in degrees, strictly between 0 and 180."""
    value = finite_float(text)
    if not 0 < value < 180:
        raise argparse.ArgumentTypeError(f"expected degrees between 0 and 180, got {text}")
    return value


def sh_degree(text: str) -> int:
    """argparse type: a spherical-harmonics degree 0..3."""
    value = _integer(text)
    if not 0 <= value <= 3:
        raise argparse.ArgumentTypeError(f"expected an SH degree 0, 1, 2 or 3, got {text}")
    return value


def background(values) -> tuple[float, float, float]:
    """The colour of ``--background`` (one value or three; black when not given)."""
    if values is None:
        return (0.0, 0.0, 0.0)
    if len(values) == 1:
        return (values[0],) * 3
    if len(values) != 3:
        raise InputError("--background takes one value or three (r g b)")
    return tuple(values)


# ------------------------------------------------------------------------------------------------ flag groups
def add_variant(parser, after_command: bool = False) -> None:
    """``--variant``; after the command it replaces one given before it (``SUPPRESS``: absent, it leaves that)."""
    parser.add_argument("--variant", default=argparse.SUPPRESS if after_command else None, help=VARIANT_HELP)


def add_output(parser, help: str, overwrite: str | None = None) -> None:
    """``-o/--output`` (required), and ``--overwrite`` with the help ``overwrite`` when the command replaces."""
    parser.add_argument("-o", "--output", type=output_path, required=True, help=help)
    if overwrite is not None:
        parser.add_argument("--overwrite", action="store_true", help=overwrite)


def add_model_input(parser, help: str, antialiased: str) -> None:
    """The model to read (``input``) and ``--[no-]antialiased`` (how it renders; default: as it was trained)."""
    parser.add_argument("input", help=help)
    parser.add_argument("--antialiased", action=argparse.BooleanOptionalAction, default=None, help=antialiased)


def add_background(parser, help: str) -> None:
    parser.add_argument("--background", type=finite_float, nargs="+", default=None, help=help)


def add_define(parser, help: str) -> None:
    """``-D KEY=VALUE`` (repeatable): the parameters of a Mitsuba scene, as ``mitsuba -D``."""
    parser.add_argument("-D", "--define", action="append", default=None, metavar="KEY=VALUE", help=help)


#: the viewer's options: (flag, dest); their defaults are ``ViewerConfig``'s (None on the command line: not given)
VIEWER_OPTIONS = (("--port", "port"), ("--host", "host"), ("--max-size", "max_size"), ("--moving-size", "moving_size"))


def add_viewer_options(parser) -> None:
    """Where the browser viewer serves and how large its frames are (``mi_gaussians.viewer.ViewerConfig``; the sizes
    within the ranges of the viewer's own size sliders)."""
    from ..viewer import MAX_SIZE_RANGE, MOVING_SIZE_RANGE, ViewerConfig

    v = ViewerConfig()
    parser.add_argument("--port", type=port_number, default=None, help=f"viewer port (default {v.port})")
    parser.add_argument("--host", default=None, help=f"viewer address (default {v.host}; 0.0.0.0: every interface)")
    parser.add_argument("--max-size", type=sized(*MAX_SIZE_RANGE, "the viewer's size slider"), default=None,
                        help=f"longest image side at rest, {MAX_SIZE_RANGE[0]} to {MAX_SIZE_RANGE[1]} "
                             f"(default {v.max_size})")
    parser.add_argument("--moving-size", type=sized(*MOVING_SIZE_RANGE, "the viewer's size slider"), default=None,
                        help=f"longest image side while the camera moves, {MOVING_SIZE_RANGE[0]} to "
                             f"{MOVING_SIZE_RANGE[1]} (default {v.moving_size})")


def viewer_options_given(args) -> list[str]:
    """The viewer's options given on the command line."""
    return [flag for flag, dest in VIEWER_OPTIONS if getattr(args, dest, None) is not None]


def viewer_config(args):
    """The ``ViewerConfig`` of the options (``ViewerConfig``'s defaults for those not given)."""
    import dataclasses

    from ..viewer import ViewerConfig

    return dataclasses.replace(ViewerConfig(), **{dest: getattr(args, dest) for _, dest in VIEWER_OPTIONS
                                                  if getattr(args, dest, None) is not None})


def check_viewer(args) -> None:
    """Before anything starts (a model loaded, a run trained): the viewer's address can be served (the host resolves,
    the port can be bound) and its largest frame fits in memory; one line otherwise."""
    import socket

    from ..memory import check_image

    cfg = viewer_config(args)
    try:
        infos = socket.getaddrinfo(cfg.host, cfg.port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError, ValueError) as e:
        raise InputError(f"--host {cfg.host}: not an address this machine can serve at "
                         f"({getattr(e, 'strerror', None) or e})") from None
    family, _, _, _, address = infos[0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
    except (OSError, OverflowError) as e:
        raise InputError(f"--host {cfg.host} --port {cfg.port}: cannot serve there "
                         f"({getattr(e, 'strerror', None) or e})") from None
    try:
        check_image(cfg.max_size, cfg.max_size, "--max-size", advice="give a smaller --max-size")
    except ValueError as e:
        raise InputError(str(e)) from None


def start_viewer(viewer, args) -> None:
    """Start serving; an address that cannot be served is the user's input error, and one beyond this machine is
    served with a warning (the viewer has no authentication)."""
    cfg = viewer_config(args)
    try:
        viewer.start()
    except (OSError, OverflowError) as e:
        raise InputError(f"--host {cfg.host} --port {cfg.port}: cannot serve there "
                         f"({getattr(e, 'strerror', None) or e})") from None
    if not is_loopback(cfg.host):
        import socket

        from .errors import warn

        warn(f"--host {cfg.host}: the viewer serves the model, its cameras and reference images to every machine "
             f"that can reach this one, without authentication (they open http://{socket.gethostname()}:{cfg.port};"
             " --host 127.0.0.1 keeps it on this machine)")


def is_loopback(host: str) -> bool:
    """Whether ``host`` names this machine only (127.0.0.0/8, ::1, localhost)."""
    import ipaddress
    import socket

    try:
        addresses = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except socket.gaierror:
        return False
    try:
        return all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addresses)
    except ValueError:
        return False


# ------------------------------------------------------------------------------------------------------ checks
def model_suffixes() -> tuple[str, ...]:
    """The model formats every command reads (``mi_gaussians.model.web_formats.FORMATS``)."""
    from ..model.web_formats import FORMATS

    return FORMATS


def is_model(path: Path) -> bool:
    return path.suffix.lower() in model_suffixes()


def existing(path: str | Path) -> Path:
    """``path`` as a Path, or the one-line error that it is not there."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: not found")
    return p


def set_variant(name: str | None) -> None:
    """Select the Mitsuba variant ``name`` (default: ``cuda_ad_rgb`` when a CUDA device exists, else
    ``llvm_ad_rgb``)."""
    import drjit as dr
    import mitsuba as mi

    variant = name or ("cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb")
    if variant not in SUPPORTED_VARIANTS:
        known = "a Mitsuba variant mi-gs cannot use" if variant in mi.variants() else "not a Mitsuba variant"
        raise InputError(f"--variant {variant}: {known} (mi-gs runs on {' or '.join(SUPPORTED_VARIANTS)})")
    if variant.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
        raise InputError(f"--variant {variant}: no CUDA device or driver is available on this machine "
                         "(use llvm_ad_rgb)")
    mi.set_variant(variant)
