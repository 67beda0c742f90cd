"""glTF 2.0 with Khronos' ``KHR_gaussian_splatting`` (``.glb`` and ``.gltf``), read and written, from and to the
raw parameters of :class:`~mi_gaussians.model.gaussians.Gaussians` (NumPy dicts keyed by ``PARAMETER_NAMES``).

Written as the extension's README (KhronosGroup/glTF ``extensions/2.0/Khronos/KHR_gaussian_splatting``, release
candidate) says: one mesh of one ``POINTS`` primitive (``mode`` 0) on one node without a transform, its
``extensions.KHR_gaussian_splatting`` = ``{"kernel": "ellipse", "colorSpace": "srgb_rec709_display" or
"lin_rec709_display", "projection": "perspective", "sortingMethod": "cameraDistance"}``, and these attributes, one
tightly packed buffer view each::

    POSITION                                    VEC3 float      the mean (min and max given, as glTF requires)
    COLOR_0                                     VEC4 ubyte n.   fallback colour for viewers without the extension:
                                                                clamp(0.5 + SH_C0 * f_dc) (linearized when the colour
                                                                space is sRGB: glTF's COLOR_0 is linear) and opacity
    KHR_gaussian_splatting:ROTATION             VEC4 float      unit quaternion, glTF's (x, y, z, w) order
    KHR_gaussian_splatting:SCALE                VEC3 float      linear: exp(scales)
    KHR_gaussian_splatting:OPACITY              SCALAR float    linear: sigmoid(opacities)
    KHR_gaussian_splatting:SH_DEGREE_0_COEF_0   VEC3 float      f_dc (RGB)
    KHR_gaussian_splatting:SH_DEGREE_l_COEF_n   VEC3 float      band l (1..the model's degree), order m = -l..l

The SH basis and its signs are the reference's (the extension's appendix), so the coefficients are the PLY's,
reordered. The frame is glTF's: +Y up, +Z forward, right-handed (LUF; metres: the model's units are kept), turned
from the PLY's RDF frame as the reference SPZ library and PlayCanvas splat-transform do, by the 180-degree rotation
about z: positions (-x, -y, z), quaternions (w, -x, -y, z), SH coefficients odd in x + y negated.

A ``.glb`` holds the JSON and the binary buffer; a ``.gltf`` is the JSON alone, its buffer embedded as a base64
``data:`` URI (one file, 4/3 the size). Reading takes other tools' files too: every component type the extension
allows (normalized integers dequantized as glTF says), strided views, buffers in the GLB, in ``data:`` URIs or in
files beside a ``.gltf``, several splat primitives, and node transforms (the global matrix of each node applied to
means, covariances and, by its rotation, the SH). Other primitives are ignored; sparse accessors, compressed views and
required extensions other than these are refused with one line.
"""

from __future__ import annotations

import base64
import binascii
import json
import re
import struct
import urllib.parse
from pathlib import Path

import numpy as np

from ..conventions import SH_C0, logit, sh_coeff_count, sh_degree_from_coeff_count, sigmoid
from .frames import flip_axes, quat_to_matrix, transform

EXT = "KHR_gaussian_splatting"
PREFIX = EXT + ":"
#: The model's colour spaces (``mi-gs render --color-space``) and the extension's names for them.
COLOR_SPACES = {"srgb": "srgb_rec709_display", "linear": "lin_rec709_display"}
#: glTF's frame (LUF) from the model's (RDF): x' = diag(LUF_FROM_RDF) x (a rotation; its own inverse).
LUF_FROM_RDF = (-1.0, -1.0, 1.0)
GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
FLOAT, UNSIGNED_BYTE, ARRAY_BUFFER, POINTS = 5126, 5121, 34962, 0
#: componentType -> (NumPy type, divisor of a normalized value, smallest normalized value)
COMPONENTS = {5120: ("<i1", 127.0, -1.0), 5121: ("<u1", 255.0, 0.0), 5122: ("<i2", 32767.0, -1.0),
              5123: ("<u2", 65535.0, 0.0), 5125: ("<u4", None, None), 5126: ("<f4", None, None)}
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
#: Required extensions a reader may meet and read all the same (mesh quantization only widens the types).
READABLE_REQUIRED = {EXT, "KHR_mesh_quantization"}
OPACITY_EPS = 1e-7
SCALE_FLOOR = 1e-9


def _fail(path, msg: str):
    raise ValueError(f"{path}: {msg}")


def _generator() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"mi-gaussians {version('mi-gaussians')}"
    except PackageNotFoundError:
        return "mi-gaussians"


# ---------------------------------------------------------------------------------------------------- writing
def _attributes(p: dict, color_space: str) -> list[tuple[str, np.ndarray, int, bool]]:
    """(semantic, (N, width) array, componentType, normalized) of each attribute, in glTF's frame."""
    from ..imwrite import srgb_to_linear

    g = flip_axes(p, LUF_FROM_RDF)
    q = np.asarray(g["rotations"], np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1), np.array([1.0, 0, 0, 0]))
    dc = np.asarray(p["sh_dc"], np.float64)
    opacity = sigmoid(np.asarray(p["opacities"], np.float64))
    base = np.clip(0.5 + SH_C0 * dc, 0.0, 1.0)
    if color_space == "srgb":
        base = srgb_to_linear(base)
    colour = np.clip(np.round(np.concatenate([base, opacity[:, None]], axis=1) * 255.0), 0, 255).astype(np.uint8)
    out = [("POSITION", np.asarray(g["means"], np.float32), FLOAT, False), ("COLOR_0", colour, UNSIGNED_BYTE, True),
           (PREFIX + "ROTATION", q[:, [1, 2, 3, 0]].astype(np.float32), FLOAT, False),
           (PREFIX + "SCALE", np.exp(np.asarray(p["scales"], np.float64)).astype(np.float32), FLOAT, False),
           (PREFIX + "OPACITY", opacity.astype(np.float32)[:, None], FLOAT, False),
           (PREFIX + "SH_DEGREE_0_COEF_0", dc.astype(np.float32), FLOAT, False)]
    sh_rest = np.asarray(g["sh_rest"], np.float32)
    for l in range(1, sh_degree_from_coeff_count(sh_rest.shape[1] + 1) + 1):
        for n in range(2 * l + 1):
            out.append((f"{PREFIX}SH_DEGREE_{l}_COEF_{n}", sh_rest[:, l * l - 1 + n], FLOAT, False))
    return out


def gltf_document(p: dict, color_space: str = "srgb") -> tuple[dict, bytes]:
    """(the glTF JSON, its one binary buffer) of the raw parameters ``p`` (``color_space``: srgb or linear, what
    the model's colours are)."""
    if color_space not in COLOR_SPACES:
        raise ValueError(f"unknown colour space {color_space!r} (expected one of {', '.join(COLOR_SPACES)})")
    n = len(p["means"])
    if n == 0:
        raise ValueError("a glTF Gaussian-splat primitive needs at least one Gaussian")
    views, accessors, attributes, chunks, offset = [], [], {}, [], 0
    for i, (name, data, component, normalized) in enumerate(_attributes(p, color_space)):
        raw = np.ascontiguousarray(data).tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw), "target": ARRAY_BUFFER})
        acc = {"bufferView": i, "componentType": component, "count": n,
               "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[data.shape[1]]}
        if normalized:
            acc["normalized"] = True
        if name == "POSITION":
            acc["min"] = [float(v) for v in data.min(axis=0)]
            acc["max"] = [float(v) for v in data.max(axis=0)]
        accessors.append(acc)
        attributes[name] = i
        chunks.append(raw + b"\0" * (-len(raw) % 4))
        offset += len(chunks[-1])
    binary = b"".join(chunks)
    doc = {"asset": {"version": "2.0", "generator": _generator()},
           "extensionsUsed": [EXT],
           "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "gaussians"}],
           "meshes": [{"name": "gaussians", "primitives": [{
               "attributes": attributes, "mode": POINTS,
               "extensions": {EXT: {"kernel": "ellipse", "colorSpace": COLOR_SPACES[color_space],
                                    "projection": "perspective", "sortingMethod": "cameraDistance"}}}]}],
           "buffers": [{"byteLength": len(binary)}], "bufferViews": views, "accessors": accessors}
    return doc, binary


def glb_bytes(p: dict, color_space: str = "srgb") -> bytes:
    """The ``.glb`` file of the raw parameters ``p``: 12-byte header, JSON chunk (space-padded), BIN chunk."""
    doc, binary = gltf_document(p, color_space)
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (struct.pack("<III", GLB_MAGIC, 2, total) + struct.pack("<II", len(text), JSON_CHUNK) + text
            + struct.pack("<II", len(binary), BIN_CHUNK) + binary)


def gltf_text(p: dict, color_space: str = "srgb") -> str:
    """The ``.gltf`` file of the raw parameters ``p``, its buffer embedded as a base64 ``data:`` URI."""
    doc, binary = gltf_document(p, color_space)
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
    return json.dumps(doc, separators=(",", ":"))


# ---------------------------------------------------------------------------------------------------- reading
def _load(path: Path) -> tuple[dict, list]:
    """(JSON, buffers: bytes, or None for one not loaded yet) of a ``.glb`` or ``.gltf`` file."""
    raw = path.read_bytes()
    glb_bin = None
    if raw[:4] == struct.pack("<I", GLB_MAGIC):
        if len(raw) < 20:
            _fail(path, f"truncated GLB header ({len(raw)} bytes)")
        _, version, length = struct.unpack_from("<III", raw)
        if version != 2:
            _fail(path, f"GLB version {version} (only glTF 2.0 is read)")
        if length > len(raw):
            _fail(path, f"truncated GLB: {len(raw)} bytes, its header says {length}")
        off, chunks = 12, []
        while off + 8 <= length:
            size, kind = struct.unpack_from("<II", raw, off)
            if off + 8 + size > length:
                _fail(path, f"truncated GLB chunk at byte {off} ({size} bytes announced)")
            chunks.append((kind, raw[off + 8: off + 8 + size]))
            off += 8 + size
        if not chunks or chunks[0][0] != JSON_CHUNK:
            _fail(path, "damaged GLB: its first chunk is not JSON")
        text = chunks[0][1]
        glb_bin = next((c for k, c in chunks[1:] if k == BIN_CHUNK), None)
    elif path.suffix.lower() == ".glb":
        _fail(path, "not a GLB file (no glTF magic)")
    else:
        text = raw
    try:
        doc = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        _fail(path, f"not glTF JSON ({' '.join(str(e).split())})")
    if not isinstance(doc, dict) or not isinstance(doc.get("asset"), dict):
        _fail(path, "not a glTF document (no \"asset\")")
    if not str(doc["asset"].get("version", "")).startswith("2."):
        _fail(path, f"glTF version {doc['asset'].get('version')!r} (only 2.x is read)")
    buffers = []
    for i, b in enumerate(doc.get("buffers") or []):
        uri = b.get("uri") if isinstance(b, dict) else None
        if uri is None:
            if i != 0 or glb_bin is None:
                _fail(path, f"buffer {i} has no uri and there is no GLB binary chunk")
            buffers.append(glb_bin)
        elif uri.startswith("data:"):
            try:
                buffers.append(base64.b64decode(uri.split(",", 1)[1], validate=True))
            except (IndexError, binascii.Error):
                _fail(path, f"buffer {i}: damaged base64 data: URI")
        elif "://" in uri or uri.startswith("/"):
            _fail(path, f"buffer {i} is not beside the file ({uri[:60]}): only data: URIs and relative files are read")
        else:
            side = path.parent / urllib.parse.unquote(uri)
            try:
                buffers.append(side.read_bytes())
            except OSError as e:
                _fail(path, f"buffer {i}: {side}: {(e.strerror or str(e)).lower()}")
    return doc, buffers


def _item(doc: dict, key: str, i, path):
    items = doc.get(key)
    if not (isinstance(i, int) and isinstance(items, list) and 0 <= i < len(items) and isinstance(items[i], dict)):
        _fail(path, f"{key}[{i}] does not exist")
    return items[i]


def _accessor(doc: dict, buffers: list, index, path) -> np.ndarray:
    """Accessor ``index`` as a (count, width) float64 array (normalized integers dequantized)."""
    acc = _item(doc, "accessors", index, path)
    where = f"accessor {index}"
    if "sparse" in acc:
        _fail(path, f"{where} is sparse (not read)")
    if acc.get("componentType") not in COMPONENTS or acc.get("type") not in WIDTHS:
        _fail(path, f"{where}: component type {acc.get('componentType')} / type {acc.get('type')!r} is not a vertex "
                    "attribute's")
    dtype, divisor, low = COMPONENTS[acc["componentType"]]
    width, count = WIDTHS[acc["type"]], acc.get("count")
    if not isinstance(count, int) or count < 0:
        _fail(path, f"{where}: bad count {count!r}")
    if "bufferView" not in acc:
        return np.zeros((count, width))
    view = _item(doc, "bufferViews", acc["bufferView"], path)
    if view.get("extensions"):
        _fail(path, f"{where}: its buffer view uses {', '.join(view['extensions'])} (compressed views are not read)")
    buf = view.get("buffer")
    if not isinstance(buf, int) or not 0 <= buf < len(buffers):
        _fail(path, f"{where}: its buffer view names buffer {buf!r}, which does not exist")
    item = np.dtype(dtype).itemsize * width
    stride = view.get("byteStride") or item
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    need = start + (stride * (count - 1) + item if count else 0)
    if stride < item or need > view.get("byteOffset", 0) + view.get("byteLength", 0) or need > len(buffers[buf]):
        _fail(path, f"{where}: {count} elements of {item} bytes (stride {stride}) do not fit its buffer view "
                    "(truncated file?)")
    data = np.ndarray((count, width), dtype, buffers[buf], start, (stride, np.dtype(dtype).itemsize))
    out = data.astype(np.float64)
    if acc.get("normalized"):
        if divisor is None:
            _fail(path, f"{where}: normalized {dtype} is not a glTF type")
        out = np.maximum(out / divisor, low)
    return out


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T          # (column-major in glTF)
    m = np.eye(4)
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    m[:3, :3] = quat_to_matrix(np.array([[w, x, y, z]]))[0] * np.asarray(node.get("scale", (1, 1, 1)), np.float64)
    m[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return m


def _mesh_instances(doc: dict, path) -> list[tuple[int, np.ndarray, str]]:
    """(mesh index, global matrix, where) of every mesh of the default scene (its nodes' hierarchy walked); without
    scenes, of every root node; without nodes, of every mesh as it is."""
    nodes = doc.get("nodes") or []
    if not nodes:
        return [(i, np.eye(4), f"mesh {i}") for i in range(len(doc.get("meshes") or []))]
    if doc.get("scenes"):
        roots = _item(doc, "scenes", doc.get("scene", 0), path).get("nodes", [])
    else:
        children = {c for n in nodes if isinstance(n, dict) for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    out, stack, seen = [], [(r, np.eye(4)) for r in roots], set()
    while stack:
        i, parent = stack.pop()
        node = _item(doc, "nodes", i, path)
        if i in seen:
            _fail(path, f"node {i} is reached twice (a cycle, or a node with two parents)")
        seen.add(i)
        m = parent @ _node_matrix(node)
        if "mesh" in node:
            out.append((node["mesh"], m, f"node {i}"))
        stack.extend((c, m) for c in node.get("children", []))
    return out


def _primitive(doc: dict, buffers: list, prim: dict, path, where: str) -> tuple[dict, str]:
    """(raw parameters in the primitive's own frame, colour space) of one splat primitive."""
    ext = prim["extensions"][EXT]
    if prim.get("mode", 4) != POINTS:
        _fail(path, f"{where}: mode {prim.get('mode', 4)}, a Gaussian-splat primitive must be POINTS (0)")
    if ext.get("kernel") != "ellipse":
        _fail(path, f"{where}: kernel {ext.get('kernel')!r} is not read (only 'ellipse')")
    space = next((k for k, v in COLOR_SPACES.items() if v == ext.get("colorSpace")), None)
    if space is None:
        _fail(path, f"{where}: colorSpace {ext.get('colorSpace')!r} is not read "
                    f"(only {', '.join(COLOR_SPACES.values())})")
    attrs = prim.get("attributes") or {}

    def get(name, width):
        if name not in attrs:
            _fail(path, f"{where}: no {name} attribute")
        a = _accessor(doc, buffers, attrs[name], path)
        if a.shape[1] != width:
            _fail(path, f"{where}: {name} has {a.shape[1]} components, {width} expected")
        if not np.all(np.isfinite(a)):
            _fail(path, f"{where}: {name} holds non-finite values")
        return a

    means, q = get("POSITION", 3), get(PREFIX + "ROTATION", 4)
    scale, opacity = get(PREFIX + "SCALE", 3), get(PREFIX + "OPACITY", 1)[:, 0]
    dc = get(PREFIX + "SH_DEGREE_0_COEF_0", 3)
    n = len(means)
    degree = 0
    while f"{PREFIX}SH_DEGREE_{degree + 1}_COEF_0" in attrs:
        degree += 1
    stray = [a for a in attrs if a.startswith(PREFIX + "SH_") and not (
        (m := re.fullmatch(re.escape(PREFIX) + r"SH_DEGREE_(\d)_COEF_\d+", a)) and int(m.group(1)) <= degree)]
    if degree > 3 or stray:
        _fail(path, f"{where}: SH bands are not contiguous up to degree 3 ({(stray or [degree])[0]})")
    rest = [get(f"{PREFIX}SH_DEGREE_{l}_COEF_{m}", 3) for l in range(1, degree + 1) for m in range(2 * l + 1)]
    if any(len(a) != n for a in (q, scale, opacity, dc, *rest)):
        _fail(path, f"{where}: its attributes do not all have POSITION's {n} elements")
    if np.any(scale < 0):
        _fail(path, f"{where}: {int(np.sum(np.any(scale < 0, axis=1)))} negative scale(s) (the extension's scales "
                    "are linear: log scales written as they are?)")
    if np.any((opacity < -1e-3) | (opacity > 1 + 1e-3)):
        bad = opacity[(opacity < -1e-3) | (opacity > 1 + 1e-3)][0]
        _fail(path, f"{where}: opacities outside 0..1 (e.g. {bad:.4g}; the extension's opacities are linear: logits "
                    "written as they are?)")
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1), np.array([0, 0, 0, 1.0]))
    p = {"means": means, "scales": np.log(np.maximum(scale, SCALE_FLOOR)), "rotations": q[:, [3, 0, 1, 2]],
         "opacities": logit(np.clip(opacity, OPACITY_EPS, 1 - OPACITY_EPS)), "sh_dc": dc,
         "sh_rest": np.stack(rest, axis=1) if rest else np.zeros((n, 0, 3))}
    return {k: v.astype(np.float32) for k, v in p.items()}, space


def read_gltf(path) -> tuple[dict[str, np.ndarray], dict]:
    """(raw parameters in the model's frame, {"color_space", "generator", "primitives"}) of the Gaussian-splat
    primitives of a ``.glb`` / ``.gltf`` file's default scene."""
    path = Path(path)
    doc, buffers = _load(path)
    unknown = sorted(set(doc.get("extensionsRequired") or []) - READABLE_REQUIRED)
    if unknown:
        _fail(path, f"requires {', '.join(unknown)}, which mi-gs does not read")
    parts, spaces = [], set()
    for mesh_index, m, where in _mesh_instances(doc, path):
        mesh = _item(doc, "meshes", mesh_index, path)
        for j, prim in enumerate(mesh.get("primitives") or []):
            if not isinstance(prim, dict) or EXT not in (prim.get("extensions") or {}):
                continue
            here = f"{where}, mesh {mesh_index} primitive {j}"
            p, space = _primitive(doc, buffers, prim, path, here)
            spaces.add(space)
            if not np.allclose(m, np.eye(4), rtol=0, atol=1e-12):
                if not np.all(np.isfinite(m)) or not np.linalg.det(m[:3, :3]) > 0:
                    _fail(path, f"{here}: its node's transform mirrors or flattens (the extension leaves such "
                                "splats undefined)")
                p = transform(p, m[:3, :3], m[:3, 3])
            parts.append(p)
    if not parts:
        _fail(path, f"no {EXT} primitive in its scene (a glTF without Gaussian splats?)")
    if len(spaces) > 1:
        _fail(path, f"primitives in different colour spaces ({', '.join(sorted(spaces))})")
    degree = max(sh_degree_from_coeff_count(p["sh_rest"].shape[1] + 1) for p in parts)
    k = sh_coeff_count(degree) - 1
    for p in parts:
        have = p["sh_rest"].shape[1]
        p["sh_rest"] = np.concatenate([p["sh_rest"], np.zeros((len(p["means"]), k - have, 3), np.float32)], axis=1)
    params = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    return flip_axes(params, LUF_FROM_RDF), {"color_space": spaces.pop(), "primitives": len(parts),
                                             "generator": str(doc["asset"].get("generator", ""))}
