"""glTF 2.0 with KHR_gaussian_splatting (mi_gaussians.model.gltf) and the changes of frame under it
(mi_gaussians.model.frames): the file's layout as the extension's README says it, exact round trips, the frame
(glTF's LUF from the PLY's RDF) checked against the SH basis itself, node transforms, other tools' files (quantized
and strided accessors, several primitives, external and embedded buffers) built here by hand, and damaged files.
The ecosystem's own readers (Khronos' validator, three.js) read our files in tests/test_export_ecosystem.py."""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from mi_gaussians.conventions import SH_C0, sh_degree_from_coeff_count
from mi_gaussians.model import frames, gltf

F = np.diag(gltf.LUF_FROM_RDF)


def _model(n=300, degree=3, seed=0) -> dict:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return {"means": rng.uniform(-3, 3, (n, 3)).astype(np.float32),
            "scales": rng.uniform(-6, -1, (n, 3)).astype(np.float32),
            "rotations": rng.normal(size=(n, 4)).astype(np.float32),
            "opacities": rng.uniform(-4, 4, n).astype(np.float32),
            "sh_dc": rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32),
            "sh_rest": rng.uniform(-0.9, 0.9, (n, k, 3)).astype(np.float32)}


def _sig(x):
    return 1 / (1 + np.exp(-np.asarray(x, np.float64)))


def _cov(p) -> np.ndarray:
    a = frames.quat_to_matrix(p["rotations"]) * np.exp(np.asarray(p["scales"], np.float64))[:, None, :]
    return a @ np.transpose(a, (0, 2, 1))


def assert_same_shapes(a, b, rel: float) -> None:
    """Covariances ``a`` and ``b`` (N, 3, 3) equal up to ``rel`` of each Gaussian's largest entry."""
    err = np.abs(a - b).max(axis=(1, 2)) / np.abs(b).max(axis=(1, 2))
    assert err.max() <= rel, (err.max(), int(err.argmax()))


def _colours(p, dirs) -> np.ndarray:
    """(N, 3) SH colour of each Gaussian along its own direction ``dirs[i]`` (before the +0.5 and the clamp)."""
    degree = sh_degree_from_coeff_count(p["sh_rest"].shape[1] + 1)
    b = frames.sh_basis(dirs, degree)
    coeffs = np.concatenate([np.asarray(p["sh_dc"], np.float64)[:, None], np.asarray(p["sh_rest"], np.float64)], 1)
    return np.einsum("nk,nkc->nc", b, coeffs)


def parse_glb(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == 0x4E4F534A and jlen % 4 == 0
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == 0x004E4942 and 28 + jlen + blen == len(data)
    return json.loads(data[20:20 + jlen]), data[28 + jlen:]


def pack_glb(doc: dict, binary: bytes) -> bytes:
    """A GLB of the JSON ``doc`` and the binary chunk ``binary`` (padded as the GLB layout says)."""
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    return (struct.pack("<III", 0x46546C67, 2, 28 + len(text) + len(binary)) + struct.pack("<II", len(text), 0x4E4F534A)
            + text + struct.pack("<II", len(binary), 0x004E4942) + binary)


def attribute(doc, binary, name) -> np.ndarray:
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][name]]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {5126: "<f4", 5121: "u1"}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    assert "byteStride" not in view and view["byteOffset"] % 4 == 0
    return np.frombuffer(binary, dtype, acc["count"] * width, view["byteOffset"]).reshape(acc["count"], width)


# ---------------------------------------------------------------------------------------------------- our files
def test_glb_layout_is_the_extensions():
    p = _model()
    doc, binary = parse_glb(gltf.glb_bytes(p))
    assert doc["asset"]["version"] == "2.0" and doc["extensionsUsed"] == ["KHR_gaussian_splatting"]
    assert "extensionsRequired" not in doc                                # (viewers without it show points)
    assert doc["scenes"] == [{"nodes": [0]}] and set(doc["nodes"][0]) == {"mesh", "name"}     # no transform
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 0 and prim["extensions"] == {"KHR_gaussian_splatting": {
        "kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective",
        "sortingMethod": "cameraDistance"}}
    names = ["POSITION", "COLOR_0"] + [f"KHR_gaussian_splatting:{a}" for a in ("ROTATION", "SCALE", "OPACITY")] + [
        f"KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{m}" for l in range(4) for m in range(2 * l + 1)]
    assert list(prim["attributes"]) == names
    for name in names:
        acc = doc["accessors"][prim["attributes"][name]]
        want = {"COLOR_0": (5121, "VEC4"), "KHR_gaussian_splatting:ROTATION": (5126, "VEC4"),
                "KHR_gaussian_splatting:OPACITY": (5126, "SCALAR")}.get(name, (5126, "VEC3"))
        assert (acc["componentType"], acc["type"], acc["count"]) == (*want, 300)
        assert acc.get("normalized", False) == (name == "COLOR_0")
    pos = attribute(doc, binary, "POSITION")
    np.testing.assert_array_equal(pos, p["means"] * gltf.LUF_FROM_RDF)          # (-x, -y, z): glTF's LUF
    acc = doc["accessors"][prim["attributes"]["POSITION"]]
    assert acc["min"] == pos.min(0).tolist() and acc["max"] == pos.max(0).tolist()
    q = p["rotations"] / np.linalg.norm(p["rotations"], axis=1, keepdims=True)
    np.testing.assert_allclose(attribute(doc, binary, "KHR_gaussian_splatting:ROTATION"),
                               np.c_[-q[:, 1], -q[:, 2], q[:, 3], q[:, 0]], atol=1e-7)   # (x, y, z, w) of D R D
    np.testing.assert_allclose(attribute(doc, binary, "KHR_gaussian_splatting:SCALE"), np.exp(p["scales"]),
                               rtol=1e-6)
    np.testing.assert_allclose(attribute(doc, binary, "KHR_gaussian_splatting:OPACITY")[:, 0],
                               _sig(p["opacities"]), rtol=1e-6)
    np.testing.assert_array_equal(attribute(doc, binary, "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0"), p["sh_dc"])
    signs = frames.sh_flip_signs(gltf.LUF_FROM_RDF)
    for l in range(1, 4):
        for m in range(2 * l + 1):
            i = l * l - 1 + m
            np.testing.assert_array_equal(
                attribute(doc, binary, f"KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{m}"), p["sh_rest"][:, i] * signs[i])
    # COLOR_0 (fallback): glTF's colours are linear, so an sRGB model's base colour is decoded
    from mi_gaussians.imwrite import srgb_to_linear

    base = np.clip(0.5 + SH_C0 * p["sh_dc"].astype(np.float64), 0, 1)
    colour = attribute(doc, binary, "COLOR_0").astype(np.float64) / 255
    assert np.abs(colour[:, :3] - srgb_to_linear(base)).max() <= 0.5 / 255 + 1e-9
    assert np.abs(colour[:, 3] - _sig(p["opacities"])).max() <= 0.5 / 255 + 1e-9
    lin, lin_bin = parse_glb(gltf.glb_bytes(p, "linear"))
    ext = lin["meshes"][0]["primitives"][0]["extensions"]["KHR_gaussian_splatting"]
    assert ext["colorSpace"] == "lin_rec709_display"
    assert np.abs(attribute(lin, lin_bin, "COLOR_0")[:, :3] / 255 - base).max() <= 0.5 / 255 + 1e-9


def test_round_trips_are_exact(tmp_path):
    p = _model(n=200, degree=2, seed=1)
    for name, data in (("m.glb", gltf.glb_bytes(p)), ("m.gltf", gltf.gltf_text(p, "linear").encode())):
        (tmp_path / name).write_bytes(data)
        back, meta = gltf.read_gltf(tmp_path / name)
        assert meta == {"color_space": "srgb" if name == "m.glb" else "linear", "primitives": 1,
                        "generator": meta["generator"]} and meta["generator"].startswith("mi-gaussians")
        for key in ("means", "scales", "sh_dc", "sh_rest"):
            np.testing.assert_allclose(back[key], p[key], rtol=0, atol=2e-6 if key == "scales" else 0)
        assert np.abs(_sig(back["opacities"]) - _sig(p["opacities"])).max() < 1e-6
        assert_same_shapes(_cov(back), _cov(p), 1e-5)
    doc = json.loads((tmp_path / "m.gltf").read_text())
    assert doc["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")


def test_frame_change_keeps_every_colour_and_shape():
    """The glTF file's coefficients, evaluated with the reference basis along the glTF-frame direction F d, give the
    colour the model gives along d (both for the axis flips and for any rotation); the numpy basis is the
    renderer's."""
    import mitsuba as mi

    from mi_gaussians.model.sh import sh_basis

    rng = np.random.default_rng(5)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ours = np.array([np.array(x) for x in sh_basis(mi.Vector3f(*map(mi.Float, d.T.astype(np.float32))), 3)]).T
    np.testing.assert_allclose(frames.sh_basis(d, 3), ours, atol=1e-6)
    p = _model(n=64, degree=3, seed=2)
    for signs in (gltf.LUF_FROM_RDF, (1, -1, -1), (1, 1, -1)):                   # glTF, RUB, a mirror
        g = frames.flip_axes(p, signs)
        np.testing.assert_allclose(_colours(g, d * signs), _colours(p, d), atol=1e-5)
        assert_same_shapes(_cov(g), np.diag(signs) @ _cov(p) @ np.diag(signs), 1e-5)
    # the least-squares band rotation is the sign table for a flip, and a rotation for any turn
    for w, s in zip(frames.sh_rotation(F, 3), np.split(frames.sh_flip_signs(gltf.LUF_FROM_RDF), [3, 8])):
        np.testing.assert_allclose(w, np.diag(s), atol=1e-12)
    rot = frames.quat_to_matrix(rng.normal(size=(1, 4)))[0]
    t = frames.transform(p, 2.5 * rot, (1.0, -2.0, 0.5))
    np.testing.assert_allclose(t["means"], p["means"] @ (2.5 * rot).T + [1.0, -2.0, 0.5], atol=1e-5)
    assert_same_shapes(_cov(t), 6.25 * rot @ _cov(p) @ rot.T, 1e-4)
    np.testing.assert_allclose(_colours(t, d @ rot.T), _colours(p, d), atol=1e-5)
    m = rot @ np.diag([1.0, 2.0, 0.5])                                       # not a similarity: axes re-derived
    t = frames.transform(p, m)
    assert_same_shapes(_cov(t), m @ _cov(p) @ m.T, 1e-4)
    with pytest.raises(ValueError, match="mirrors"):
        frames.transform(p, np.diag([1.0, 1.0, -1.0]))


# ---------------------------------------------------------------------------------------------------- other files
class Builder:
    """A glTF document assembled by hand, as another tool might write it: accessors of any component type, strided
    (interleaved) views, several buffers."""

    def __init__(self):
        self.doc = {"asset": {"version": "2.0", "generator": "a test"}, "extensionsUsed": ["KHR_gaussian_splatting"],
                    "buffers": [], "bufferViews": [], "accessors": [], "meshes": [], "nodes": []}
        self.chunks: list[bytearray] = []

    def buffer(self) -> int:
        self.chunks.append(bytearray())
        self.doc["buffers"].append({"byteLength": 0})
        return len(self.chunks) - 1

    def view(self, data: bytes, buffer: int = 0, stride: int | None = None) -> int:
        chunk = self.chunks[buffer]
        chunk.extend(b"\0" * (-len(chunk) % 4))
        v = {"buffer": buffer, "byteOffset": len(chunk), "byteLength": len(data)}
        if stride:
            v["byteStride"] = stride
        chunk.extend(data)
        self.doc["buffers"][buffer]["byteLength"] = len(chunk)
        self.doc["bufferViews"].append(v)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, values: np.ndarray, component: int = 5126, normalized: bool = False, view: int | None = None,
                 offset: int = 0, buffer: int = 0) -> int:
        values = np.asarray(values)
        dtype = {5120: "<i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5126: "<f4"}[component]
        if view is None:
            view = self.view(values.astype(dtype).tobytes(), buffer)
        acc = {"bufferView": view, "byteOffset": offset, "componentType": component, "count": len(values),
               "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[values.shape[1]]}
        if normalized:
            acc["normalized"] = True
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def mesh(self, primitives: list[dict]) -> int:
        self.doc["meshes"].append({"primitives": primitives})
        return len(self.doc["meshes"]) - 1

    def glb(self) -> bytes:
        assert len(self.chunks) == 1
        return pack_glb(self.doc, bytes(self.chunks[0]))


def splat_primitive(b: Builder, p: dict, quantized: bool = False) -> dict:
    """A KHR_gaussian_splatting primitive of ``p`` (raw parameters taken as already in glTF's frame). Quantized: the
    rotation as normalized shorts, the scale as normalized unsigned shorts, the opacity as normalized bytes, and the
    position interleaved with the DC colour in one strided view."""
    q = np.asarray(p["rotations"], np.float64)
    q = (q / np.linalg.norm(q, axis=1, keepdims=True))[:, [1, 2, 3, 0]]
    scale, opacity = np.exp(np.asarray(p["scales"], np.float64)), _sig(p["opacities"])[:, None]
    attrs = {}
    if quantized:
        rows = np.zeros(len(q), [("pos", "<f4", 3), ("dc", "<f4", 3)])
        rows["pos"], rows["dc"] = p["means"], p["sh_dc"]
        v = b.view(rows.tobytes(), stride=24)
        attrs["POSITION"] = b.accessor(p["means"], view=v)
        attrs["KHR_gaussian_splatting:SH_DEGREE_0_COEF_0"] = b.accessor(p["sh_dc"], view=v, offset=12)
        attrs["KHR_gaussian_splatting:ROTATION"] = b.accessor(np.round(q * 32767), 5122, True)
        attrs["KHR_gaussian_splatting:SCALE"] = b.accessor(np.round(scale * 65535), 5123, True)
        attrs["KHR_gaussian_splatting:OPACITY"] = b.accessor(np.round(opacity * 255), 5121, True)
    else:
        attrs["POSITION"] = b.accessor(p["means"])
        attrs["KHR_gaussian_splatting:ROTATION"] = b.accessor(q)
        attrs["KHR_gaussian_splatting:SCALE"] = b.accessor(scale)
        attrs["KHR_gaussian_splatting:OPACITY"] = b.accessor(opacity)
        attrs["KHR_gaussian_splatting:SH_DEGREE_0_COEF_0"] = b.accessor(p["sh_dc"])
    for l in range(1, sh_degree_from_coeff_count(p["sh_rest"].shape[1] + 1) + 1):
        for m in range(2 * l + 1):
            attrs[f"KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{m}"] = b.accessor(p["sh_rest"][:, l * l - 1 + m])
    pos = np.asarray(p["means"])
    b.doc["accessors"][attrs["POSITION"]].update(min=pos.min(0).tolist(), max=pos.max(0).tolist())
    return {"attributes": attrs, "mode": 0, "extensions": {"KHR_gaussian_splatting": {
        "kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}}


def scene_of_two(seed: int = 3) -> tuple[Builder, dict, dict, np.ndarray]:
    """A scene of a parent node (translation, rotation, uniform scale) whose child (a column-major matrix) holds a
    mesh of two splat primitives, degree 2 (float) and degree 0 (quantized), beside a triangle mesh on a node of its
    own. Returns (builder, primitive A, primitive B, the child's global 4x4 matrix)."""
    a, bq = _model(n=120, degree=2, seed=seed), _model(n=80, degree=0, seed=seed + 1)
    bq["scales"] = np.minimum(bq["scales"], -0.2).astype(np.float32)           # (normalized: scales <= 1)
    b = Builder()
    b.buffer()
    mesh = b.mesh([splat_primitive(b, a), splat_primitive(b, bq, quantized=True)])
    tri = b.accessor(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32))
    b.doc["accessors"][tri].update(min=[0, 0, 0], max=[1, 1, 0])
    other = b.mesh([{"attributes": {"POSITION": tri}}])
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    child = np.eye(4)
    child[:3, :3] = frames.quat_to_matrix(rng.normal(size=(1, 4)))[0]
    child[:3, 3] = [0.5, 0.0, -1.0]
    b.doc["nodes"] = [{"children": [1], "translation": [1.0, 2.0, 3.0], "rotation": [q[1], q[2], q[3], q[0]],
                       "scale": [2.0, 2.0, 2.0]},
                      {"mesh": mesh, "matrix": child.T.reshape(-1).tolist()}, {"mesh": other}]
    b.doc["scenes"], b.doc["scene"] = [{"nodes": [0, 2]}], 0
    parent = np.eye(4)
    parent[:3, :3] = frames.quat_to_matrix(q[None])[0] * 2.0
    parent[:3, 3] = [1.0, 2.0, 3.0]
    return b, a, bq, parent @ child


def expected_scene(a: dict, bq: dict, m: np.ndarray) -> dict:
    """What the scene of :func:`scene_of_two` is in the model's frame (B's SH padded to A's degree with zeros)."""
    parts = [frames.transform(x, m[:3, :3], m[:3, 3]) for x in (a, bq)]
    parts[1]["sh_rest"] = np.zeros((80, 8, 3), np.float32)
    return frames.flip_axes({k: np.concatenate([parts[0][k], parts[1][k]]) for k in parts[0]}, gltf.LUF_FROM_RDF)


def test_reads_other_tools_files(tmp_path):
    b, a, bq, m = scene_of_two()
    (tmp_path / "s.glb").write_bytes(b.glb())
    back, meta = gltf.read_gltf(tmp_path / "s.glb")
    assert meta["primitives"] == 2 and meta["generator"] == "a test"
    want = expected_scene(a, bq, m)
    np.testing.assert_allclose(back["means"], want["means"], atol=1e-5)
    assert_same_shapes(_cov(back), _cov(want), 1e-3)
    np.testing.assert_allclose(back["sh_rest"], want["sh_rest"], atol=1e-5)
    np.testing.assert_allclose(back["sh_dc"], want["sh_dc"], atol=0)
    assert np.abs(_sig(back["opacities"]) - _sig(want["opacities"])).max() <= 0.5 / 255 + 1e-6
    # the same document as a .gltf: one buffer in a file beside it, as most exporters write
    doc = json.loads(json.dumps(b.doc))
    doc["buffers"][0]["uri"] = "s%20data.bin"
    (tmp_path / "s data.bin").write_bytes(bytes(b.chunks[0]))
    (tmp_path / "s.gltf").write_text(json.dumps(doc))
    again, _ = gltf.read_gltf(tmp_path / "s.gltf")
    assert all(np.array_equal(again[k], back[k]) for k in back)
    # no scenes: the root nodes; no nodes: the meshes as they are
    doc2 = json.loads(json.dumps(doc))
    del doc2["scenes"], doc2["scene"]
    (tmp_path / "s2.gltf").write_text(json.dumps(doc2))
    assert np.array_equal(gltf.read_gltf(tmp_path / "s2.gltf")[0]["means"], back["means"])
    doc2["nodes"] = []
    (tmp_path / "s3.gltf").write_text(json.dumps(doc2))
    np.testing.assert_allclose(gltf.read_gltf(tmp_path / "s3.gltf")[0]["means"][:120],
                               a["means"] * gltf.LUF_FROM_RDF, atol=0)


def _valid_doc() -> tuple[dict, bytes]:
    return gltf.gltf_document(_model(n=10, degree=1, seed=9))


def _gltf_with(change) -> bytes:
    doc, binary = _valid_doc()
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
    change(doc)
    return json.dumps(doc).encode()


def _attr(doc, name):
    return doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][name]]


def _put_floats(doc, name, values):
    """Replace an attribute's data by ``values`` (float32) in the embedded buffer."""
    binary = bytearray(base64.b64decode(doc["buffers"][0]["uri"].split(",")[1]))
    view = doc["bufferViews"][_attr(doc, name)["bufferView"]]
    data = np.asarray(values, "<f4").tobytes()
    binary[view["byteOffset"]:view["byteOffset"] + len(data)] = data
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(binary)).decode()


PREFIX = "KHR_gaussian_splatting:"


@pytest.mark.parametrize("name, data, words", [
    ("a.glb", b"glTF" + struct.pack("<II", 2, 4000) + bytes(20), "truncated GLB: 32 bytes"),
    ("b.glb", b"not a glb at all", "not a GLB file"),
    ("c.gltf", b"{not json", "not glTF JSON"),
    ("d.gltf", b'{"asset": {"version": "1.0"}}', "glTF version '1.0'"),
    ("e.gltf", _gltf_with(lambda d: d.update(extensionsRequired=["KHR_draco_mesh_compression"])),
     "requires KHR_draco_mesh_compression, which mi-gs does not read"),
    ("f.gltf", _gltf_with(lambda d: d["meshes"][0]["primitives"][0].pop("extensions")), "no KHR_gaussian_splatting"),
    ("g.gltf", _gltf_with(lambda d: _put_floats(d, PREFIX + "SCALE", -np.ones((10, 3)))), "10 negative scale(s)"),
    ("h.gltf", _gltf_with(lambda d: _put_floats(d, PREFIX + "OPACITY", np.full(10, 3.5))), "opacities outside 0..1"),
    ("i.gltf", _gltf_with(lambda d: _attr(d, PREFIX + "ROTATION").update(sparse={"count": 1})), "is sparse"),
    ("j.gltf", _gltf_with(lambda d: d["meshes"][0]["primitives"][0]["attributes"].pop(PREFIX + "OPACITY")),
     "no KHR_gaussian_splatting:OPACITY attribute"),
    ("k.gltf", _gltf_with(lambda d: d["meshes"][0]["primitives"][0]["attributes"].update(
        {PREFIX + "SH_DEGREE_3_COEF_0": 0})), "not contiguous"),
    ("l.gltf", _gltf_with(lambda d: d["nodes"][0].update(scale=[1, 1, -1])), "mirrors or flattens"),
    ("m.gltf", _gltf_with(lambda d: d["buffers"][0].update(uri="missing.bin")), "missing.bin: no such file"),
    ("n.gltf", _gltf_with(lambda d: d["buffers"][0].update(uri="https://example.org/x.bin")), "is not beside"),
    ("o.gltf", _gltf_with(lambda d: _attr(d, "POSITION").update(count=99)), "do not fit its buffer view"),
    ("p.gltf", _gltf_with(lambda d: d["meshes"][0]["primitives"][0]["extensions"]["KHR_gaussian_splatting"].update(
        kernel="blob")), "kernel 'blob'"),
    ("q.gltf", _gltf_with(lambda d: d["meshes"][0]["primitives"][0].update(mode=4)), "must be POINTS"),
    ("r.gltf", _gltf_with(lambda d: _put_floats(d, "POSITION", np.full((10, 3), np.nan))), "non-finite"),
])
def test_damaged_files_give_one_line(tmp_path, name, data, words):
    from mi_gaussians.model.web_formats import read_model

    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(ValueError) as e:
        read_model(path)
    assert str(e.value).startswith(f"{path}: ") and words in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_writer_refuses_what_the_format_cannot_hold():
    with pytest.raises(ValueError, match="at least one Gaussian"):
        gltf.glb_bytes(_model(n=0, degree=0))
    with pytest.raises(ValueError, match="unknown colour space 'acescg'"):
        gltf.glb_bytes(_model(n=3), "acescg")


def test_written_path_is_atomic(tmp_path):
    from mi_gaussians.model.web_formats import read_model, write_model

    p = _model(n=50, degree=1)
    for name in ("a.glb", "a.gltf"):
        write_model(tmp_path / name, p, color_space="linear")
        assert np.array_equal(read_model(tmp_path / name)[0]["sh_dc"], p["sh_dc"])
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.glb", "a.gltf"]        # no temporary files left


def test_cli_export_records_the_colour_space(tmp_path):
    """``mi-gs export -o x.glb`` tags the colours as the model's: a glTF input's own tag, else the dataset of the run
    beside the model, else sRGB; ``--color-space`` says otherwise."""
    import shutil

    from mi_gaussians.config import TrainConfig
    from mi_gaussians.run_folder import RunRecord
    from test_cli import run

    root = Path(__file__).resolve().parents[1]
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    shutil.copy(root / "scenes" / "tiny_gaussians.ply", run_dir / "point_cloud.ply")
    RunRecord(dataset=str(root / "tests" / "data" / "tiny_colmap"), train=TrainConfig()).write(run_dir)

    def export(src, name, *extra):
        r = run("export", src, "-o", tmp_path / name, *extra)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)["color_space"], r.stderr

    assert export(run_dir / "point_cloud.ply", "a.glb") == ("srgb", "")
    assert export(run_dir / "point_cloud.ply", "lin.gltf", "--color-space", "linear")[0] == "linear"
    assert export(tmp_path / "lin.gltf", "b.glb") == ("linear", "")              # (the input's own tag)
    r = run("export", tmp_path / "lin.gltf", "-o", tmp_path / "lin.spz")
    assert r.returncode == 0 and "cannot record that the colours of" in r.stderr and "--color-space linear" in r.stderr
    (run_dir / "config.json").write_text('{"dataset": 3}')                      # (one warning for the record)
    space, err = export(run_dir / "point_cloud.ply", "c.glb")
    assert space == "srgb" and err.startswith("mi-gs: warning: rendering with the default settings: ") and \
        err.count("\n") == 1, err
    space, err = export(run_dir / "point_cloud.ply", "d.glb", "--no-antialiased")
    assert space == "srgb" and err.startswith("mi-gs: warning: writing the colours as sRGB (give --color-space") and \
        err.count("\n") == 1, err
