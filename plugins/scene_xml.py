"""A Mitsuba scene file that renders a 3DGS ``.ply`` with the ``gaussian_splatting`` integrator.

``write_gaussian_scene`` writes the scene ``mi-gs optimize scene.xml`` leaves beside its model (``gaussians.xml``):
the integrator, the camera, and an ``ellipsoids`` shape loading the PLY. The camera is the ``perspective`` sensor
dictionary of :meth:`Camera.to_mitsuba <mi_gaussians.data.camera.Camera.to_mitsuba>` written as XML, so the sensor's
formulas live in one place.
"""

from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from mi_gaussians.data.camera import Camera
from mi_gaussians.io_utils import atomic_write_text

from .contract import ANTIALIASED, BACKGROUND, COLOR_SPACE, COLOR_SPACES, INTEGRATOR

_INDENT = "    "


def _number(v: float) -> str:
    return f"{float(v):.9g}"


def _property(name: str, value, depth: int) -> list[str]:
    """One ``mi.load_dict`` entry as XML lines: a nested plugin (a dict with a ``type``), a transform, a boolean,
    an integer, a float, an RGB triple or a string."""
    pad = _INDENT * depth
    if isinstance(value, dict):
        return _plugin(name, value, depth)
    if hasattr(value, "matrix"):        # mi.ScalarTransform4f: its entries written shortest in the variant's precision
        matrix = " ".join(str(v) for v in np.array(value.matrix).reshape(-1))
        return [f"{pad}<transform name={quoteattr(name)}>", f"{pad}{_INDENT}<matrix value=\"{matrix}\"/>",
                f"{pad}</transform>"]
    if isinstance(value, (bool, np.bool_)):
        return [f"{pad}<boolean name={quoteattr(name)} value=\"{str(bool(value)).lower()}\"/>"]
    if isinstance(value, (int, np.integer)):
        return [f"{pad}<integer name={quoteattr(name)} value=\"{int(value)}\"/>"]
    if isinstance(value, (float, np.floating)):
        return [f"{pad}<float name={quoteattr(name)} value=\"{_number(value)}\"/>"]
    if isinstance(value, (tuple, list)) and len(value) == 3:
        rgb = ", ".join(f"{float(v):.6g}" for v in value)
        return [f"{pad}<rgb name={quoteattr(name)} value=\"{rgb}\"/>"]
    if isinstance(value, str):
        return [f"{pad}<string name={quoteattr(name)} value={quoteattr(value)}/>"]
    raise ValueError(f"scene XML: cannot write property {name!r} of type {type(value).__name__}")


def _plugin(tag: str, d: dict, depth: int, plugin_id: str | None = None) -> list[str]:
    """A ``mi.load_dict`` plugin dictionary as an XML element ``<tag type=...>`` (nested plugins keep their keys as
    tags, as Mitsuba's own ``film``, ``rfilter`` and ``sampler`` are named)."""
    pad = _INDENT * depth
    attrs = f"type={quoteattr(d['type'])}" + (f" id={quoteattr(plugin_id)}" if plugin_id else "")
    body = [line for k, v in d.items() if k != "type" for line in _property(k, v, depth + 1)]
    if not body:
        return [f"{pad}<{tag} {attrs}/>"]
    return [f"{pad}<{tag} {attrs}>", *body, f"{pad}</{tag}>"]


def integrator_dict(color_space: str = "linear", background=(0.0, 0.0, 0.0), antialiased: bool = False) -> dict:
    """The ``gaussian_splatting`` integrator as a ``mi.load_dict`` dictionary (background as an RGB triple;
    ``antialiased`` only when set, so scenes of default models stay as they were)."""
    if color_space not in COLOR_SPACES:
        raise ValueError(f"color_space must be one of {', '.join(COLOR_SPACES)}, got {color_space!r}")
    d = {"type": INTEGRATOR, COLOR_SPACE: color_space,
         BACKGROUND: tuple(float(b) for b in np.asarray(background).reshape(3))}
    if antialiased:
        d[ANTIALIASED] = True
    return d


def _header(path: Path, cam: Camera, color_space: str) -> str:
    holds = ("sRGB-encoded colours, decoded to linear radiance after blending" if color_space == "srgb"
             else "linear radiance")
    return f"""<!-- Gaussians fitted by mi-gs optimize, rendered by mi-gaussians' rasterizer inside Mitsuba:
         mi-gs render {path.name} -o render.exr
     The camera is the held-out view {cam.name!r}. color_space="{color_space}": the Gaussians hold {holds}.
     Mitsuba's own ray tracer reads the same shape: replace the <integrator> element by
         <integrator type="volprim_rf_basic"/>
     (it takes none of the gaussian_splatting parameters, which Mitsuba refuses as unreferenced, and shows the
     colours as they are stored). -->"""


def gaussian_scene_xml(path: str | os.PathLike, ply: str, cam: Camera, color_space: str = "linear",
                       background=(0.0, 0.0, 0.0), antialiased: bool = False) -> str:
    """The text of :func:`write_gaussian_scene`'s file. (Its integrator is not a ``$integrator`` parameter: Mitsuba
    refuses the gaussian_splatting properties in any other integrator, so ``-Dintegrator=...`` could not work.)"""
    integrator = integrator_dict(color_space, background, antialiased)
    lines = [_header(Path(path), cam, color_space), '<scene version="3.0.0">', ""]
    lines += _plugin("integrator", integrator, 1) + [""]
    lines += _plugin("sensor", cam.to_mitsuba(), 1, plugin_id="camera") + [""]
    lines += _plugin("shape", {"type": "ellipsoids", "filename": ply}, 1, plugin_id="gaussians")
    return "\n".join(lines + ["</scene>", ""])


def write_gaussian_scene(path: str | os.PathLike, ply: str, cam: Camera, color_space: str = "linear",
                         background=(0.0, 0.0, 0.0), antialiased: bool = False) -> None:
    """A Mitsuba scene file that renders the Gaussians of ``ply`` (a path relative to the scene file's folder) with
    the ``gaussian_splatting`` integrator from camera ``cam`` (written atomically)."""
    atomic_write_text(Path(path), gaussian_scene_xml(path, ply, cam, color_space, background, antialiased))
