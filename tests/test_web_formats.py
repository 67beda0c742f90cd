""".splat (mi_gaussians.model.web_formats) and .spz (mi_gaussians.model.spz, versions 2, 3 and 4): round trips within
each format's quantization (the bounds are the formats' step sizes), the byte layout of a hand-computed Gaussian, the
version-4 container (header, table of contents, zstd streams), the frame (the model's own, as the ecosystem's tools
store it, unless Adobe's coordinate-system extension names another), version 2 files, malformed files, and ``mi-gs
export`` / ``info`` / ``render`` on the results (glTF: tests/test_gltf_export.py; against the ecosystem's own tools:
tests/test_export_ecosystem.py)."""

from __future__ import annotations

import gzip
import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from mi_gaussians.conventions import SH_C0
from mi_gaussians.model import spz
from mi_gaussians.model import web_formats as wf
from mi_gaussians.model.frames import flip_axes

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "scenes" / "tiny_gaussians.ply"
CAMERA = ROOT / "scenes" / "tiny_gaussians_camera.json"


def _model(n=500, degree=3, seed=0) -> dict:
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


def _rotation_matrices(q):
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1)


def test_splat_round_trip_and_order(tmp_path):
    p = _model()
    path = tmp_path / "m.splat"
    wf.write_model(path, p)
    assert path.stat().st_size == 32 * 500
    back = wf.read_splat(path)
    importance = np.exp(p["scales"].astype(np.float64).sum(1)) * _sig(p["opacities"])
    order = np.argsort(-importance, kind="stable")
    np.testing.assert_array_equal(back["means"], p["means"][order])                     # float32: exact
    np.testing.assert_allclose(np.exp(back["scales"].astype(np.float64)), np.exp(p["scales"][order].astype(np.float64)),
                               rtol=1e-6)
    rgb = np.clip(0.5 + SH_C0 * p["sh_dc"][order].astype(np.float64), 0, 1)
    assert np.abs(0.5 + SH_C0 * back["sh_dc"] - rgb).max() <= 0.5 / 255 + 1e-6
    assert np.abs(_sig(back["opacities"]) - _sig(p["opacities"][order])).max() <= 0.5 / 255 + 1e-6
    err = np.abs(_rotation_matrices(back["rotations"]) - _rotation_matrices(p["rotations"][order])).max()
    assert err < 0.03                                                    # 1/256 per quaternion component
    assert back["sh_rest"].shape == (500, 0, 3)


def test_splat_bytes_of_one_gaussian():
    p = {"means": np.array([[1.0, -2.0, 0.5]], np.float32), "scales": np.array([[0.0, -1.0, 0.5]], np.float32),
         "rotations": np.array([[2.0, 0.0, 0.0, 0.0]], np.float32), "opacities": np.array([0.0], np.float32),
         "sh_dc": np.array([[0.0, (1.0 - 0.5) / SH_C0, (0.0 - 0.5) / SH_C0]], np.float32),
         "sh_rest": np.zeros((1, 3, 3), np.float32)}
    expect = struct.pack("<3f3f", 1.0, -2.0, 0.5, *np.exp([0.0, -1.0, 0.5]).astype(np.float32)) + bytes([128, 255, 0, 128]) \
        + bytes([255, 128, 128, 128])
    assert wf.splat_bytes(p) == expect


@pytest.mark.parametrize("version", [3, 4])
def test_spz_round_trip_within_quantization(tmp_path, version):
    p = _model()
    path = tmp_path / "m.spz"
    wf.write_model(path, p, antialiased=True, spz_version=version)
    back, aa = spz.read_spz(path)
    assert aa is True
    assert np.abs(back["means"] - p["means"]).max() <= 0.5 / 4096 + 1e-6
    assert np.abs(back["scales"] - p["scales"]).max() <= 0.5 / 16 + 1e-6
    assert np.abs(_sig(back["opacities"]) - _sig(p["opacities"])).max() <= 0.5 / 255 + 1e-6
    assert np.abs(back["sh_dc"] - p["sh_dc"]).max() <= 0.5 / (0.15 * 255) + 1e-6
    rest = np.abs(back["sh_rest"] - p["sh_rest"])
    assert rest[:, :3].max() <= (4 + 0.5) / 128 + 1e-6 and rest[:, 3:].max() <= (8 + 0.5) / 128 + 1e-6
    err = np.abs(_rotation_matrices(back["rotations"]) - _rotation_matrices(p["rotations"])).max()
    assert err < 0.01                                                    # 9-bit smallest three
    # a model of degree 1 keeps its degree, fewer bands are dropped on request; degree 0 has no SH stream
    one = wf.drop_sh_bands(p, 1)
    wf.write_model(path, one, spz_version=version)
    assert spz.read_spz(path)[0]["sh_rest"].shape == (500, 3, 3) and spz.read_spz(path)[1] is False
    with pytest.raises(ValueError, match="SH degree 1"):
        wf.drop_sh_bands(one, 3)
    wf.write_model(path, wf.drop_sh_bands(p, 0), spz_version=version)
    back0, _ = spz.read_spz(path)
    assert back0["sh_rest"].shape == (500, 0, 3) and np.abs(back0["means"] - p["means"]).max() <= 0.5 / 4096 + 1e-6


def test_spz_versions_hold_the_same_bytes():
    """Version 4 is version 3's sections, each in its own zstd stream behind a 32-byte header and a table of
    contents (nianticlabs/spz README, "File layout (version 4)")."""
    import zstandard

    p = _model(n=300, degree=2)
    v3 = gzip.decompress(spz.spz_bytes(p, version=3))
    v4 = spz.spz_bytes(p, version=4, antialiased=True)
    magic, version, n, degree, frac, flags, streams, toc = struct.unpack("<IIIBBBBI", v4[:20])
    assert (magic, version, n, degree, frac, flags, streams, toc) == (0x5053474E, 4, 300, 2, 12, 1, 6, 32)
    assert v4[20:32] == bytes(12)
    entries = [struct.unpack_from("<QQ", v4, 32 + 16 * i) for i in range(6)]
    assert [u for _, u in entries] == [9 * 300, 300, 3 * 300, 3 * 300, 4 * 300, 3 * 8 * 300]
    off, body = 32 + 16 * 6, b""
    for comp, size in entries:
        frame = v4[off:off + comp]
        assert frame[:4] == b"\x28\xb5\x2f\xfd"                       # a zstd frame each
        body += zstandard.ZstdDecompressor().decompress(frame, max_output_size=size)
        off += comp
    assert off == len(v4) and body == v3[16:]
    assert struct.unpack("<IIIBBBB", v3[:16]) == (0x5053474E, 3, 300, 2, 12, 0, 0)
    with pytest.raises(ValueError, match="version 2 cannot be written"):
        spz.spz_bytes(p, version=2)


def test_spz_layout_and_frame():
    """The 24-bit fixed point of the model's own (x, y, z): the frame splat-transform, the reference's ply_to_spz and
    Spark use (tests/test_export_ecosystem.py reads splat-transform's files); a file that names another frame with
    Adobe's coordinate-system extension is turned back from it."""
    p = _model(n=1, degree=1)
    p["means"][:] = [1.0, 2.0, -0.25]
    raw = gzip.decompress(spz.spz_bytes(p, version=3))
    assert struct.unpack("<IIIBBBB", raw[:16]) == (0x5053474E, 3, 1, 1, 12, 0, 0)
    fixed = [int.from_bytes(raw[16 + 3 * i:19 + 3 * i], "little", signed=True) for i in range(3)]
    assert fixed == [4096, 8192, -1024]


def _with_extensions(v4: bytes, records: bytes) -> bytes:
    """A version-4 file with extension records put between its header and its table of contents."""
    header = bytearray(v4[:32])
    header[14] |= 0x2
    struct.pack_into("<I", header, 16, 32 + len(records))
    return bytes(header) + records + v4[32:]


@pytest.mark.parametrize("frame, value", [("RUB", 4), ("LUF", 7), ("RDB", 2)])
def test_spz_coordinate_system_extension(tmp_path, frame, value):
    p = _model(n=200, degree=3, seed=4)
    signs = [1.0 if a == b else -1.0 for a, b in zip(frame, "RDF")]
    stored = flip_axes(p, signs)                                         # the data as that frame holds it
    other = struct.pack("<II", 0x12340001, 5) + b"hello"                # an unknown record, skipped
    record = struct.pack("<III", 0xADBE0003, 4, value)
    (tmp_path / "a.spz").write_bytes(_with_extensions(spz.spz_bytes(stored), other + record))
    back, _ = spz.read_spz(tmp_path / "a.spz")
    assert np.abs(back["means"] - p["means"]).max() <= 0.5 / 4096 + 1e-6
    assert np.abs(back["sh_rest"] - p["sh_rest"]).max() <= 8.5 / 128 + 1e-6
    err = np.abs(_rotation_matrices(back["rotations"]) - _rotation_matrices(p["rotations"])).max()
    assert err < 0.01
    (tmp_path / "b.spz").write_bytes(_with_extensions(spz.spz_bytes(stored), other))   # no frame named: as stored
    assert np.abs(spz.read_spz(tmp_path / "b.spz")[0]["means"] - stored["means"]).max() <= 0.5 / 4096 + 1e-6


def test_smallest_three_and_version_2(tmp_path):
    rng = np.random.default_rng(3)
    q = rng.normal(size=(2000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = spz.unpack_smallest_three(spz.pack_smallest_three(q))
    assert np.abs(_rotation_matrices(back) - _rotation_matrices(q)).max() < 0.01
    # a version-2 file (3-byte rotations), written here from the published layout
    p = _model(n=50, degree=0)
    raw = bytearray(gzip.decompress(spz.spz_bytes(p, version=3)))
    n = 50
    rot_at = 16 + 16 * n
    qn = p["rotations"] / np.linalg.norm(p["rotations"], axis=1, keepdims=True)
    qn = qn * np.where(qn[:, :1] < 0, -1, 1)
    v2 = np.clip(np.round(qn[:, 1:] * 127.5 + 127.5), 0, 255).astype(np.uint8).tobytes()
    raw[4:8] = struct.pack("<I", 2)
    raw = bytes(raw[:rot_at]) + v2 + bytes(raw[rot_at + 4 * n:])
    (tmp_path / "v2.spz").write_bytes(gzip.compress(raw))
    back, _ = spz.read_spz(tmp_path / "v2.spz")
    xyz = np.frombuffer(v2, np.uint8).reshape(n, 3) / 127.5 - 1.0               # the published decoding
    w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1)))
    np.testing.assert_allclose(back["rotations"], np.c_[w, xyz], atol=1e-6)
    near = np.abs(_rotation_matrices(back["rotations"]) - _rotation_matrices(p["rotations"])).max(axis=1)
    assert np.all(near[np.abs(qn[:, 0]) > 0.3] < 0.03)     # (v2 loses w where it is small: why v3 exists)
    assert np.abs(back["means"] - p["means"]).max() <= 0.5 / 4096 + 1e-6


@pytest.mark.parametrize("name, data, words", [
    ("a.splat", b"", "no Gaussians"),
    ("b.splat", b"\0" * 33, "whole number"),
    ("c.splat", struct.pack("<3f3f", 0, 0, 0, 0, 1, 1) + bytes(8), "scale <= 0"),
    ("d.spz", b"not gzip", "not a gzip"),
    ("e.spz", gzip.compress(b"\0" * 20, mtime=0), "not a .spz file"),
    ("f.spz", gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 5, 0, 12, 0, 0) + bytes(10), mtime=0),
     "expected for 5"),
    ("g.spz", gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 9, 1, 0, 12, 0, 0), mtime=0), "version 9"),
    ("h.spz", struct.pack("<IIIBBBB", 0x5053474E, 4, 1, 0, 12, 0, 0), "truncated .spz header"),
    ("h2.spz", struct.pack("<IIIBBBBI12x", 0x5053474E, 5, 1, 0, 12, 0, 5, 32), "version 5"),
    ("h3.spz", struct.pack("<IIIBBBBI12x", 0x5053474E, 4, 1, 4, 12, 0, 6, 32), "SH degree 4"),
    ("h4.spz", struct.pack("<IIIBBBBI12x", 0x5053474E, 4, 1, 0, 12, 0, 6, 32), "6 streams, 5 expected"),
    ("h5.spz", struct.pack("<IIIBBBBI12x", 0x5053474E, 4, 1, 0, 12, 0, 5, 32) + bytes(40), "does not fit"),
    ("h6.spz", (lambda v: v[:-3])(spz.spz_bytes(_model(n=20, degree=1))), "truncated or damaged"),
    ("h7.spz", (lambda v: v[:136] + bytes(b ^ 0x5A for b in v[136:150]) + v[150:])(spz.spz_bytes(_model(n=20))),
     "damaged zstd stream 0"),
    ("h8.spz", (lambda v: v[:32] + struct.pack("<QQ", struct.unpack_from("<Q", v, 32)[0], 999) + v[48:])(
        spz.spz_bytes(_model(n=20))), "stream 0 holds 999 bytes, 180 expected"),
    ("h9.spz", _with_extensions(spz.spz_bytes(_model(n=2)), struct.pack("<III", 0xADBE0003, 4, 12)),
     "coordinate system 12"),
    ("i.spz", gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 1, 5, 12, 0, 0), mtime=0), "SH degree 5"),
    ("j.spz", (lambda z: z[:12] + bytes(b ^ 0xFF for b in z[12:40]) + z[40:])(
        gzip.compress(bytes(range(256)) * 4, mtime=0)), "damaged"),
])
def test_malformed_files_give_one_line(tmp_path, name, data, words):
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(ValueError) as e:
        wf.read_model(path)
    assert str(path) in str(e.value) and words in str(e.value) and "\n" not in str(e.value)


def _mi_gs(*args):
    from test_cli import run               # (the installed mi-gs, outside the source tree)

    return run(*args)


def _psnr(a, b):
    return 10 * math.log10(1 / np.mean((a - b) ** 2))


def test_cli_export_info_and_render(tmp_path):
    from mi_gaussians.data.images import read_image

    ref = tmp_path / "ply.exr"
    assert _mi_gs("render", TINY, "--camera", CAMERA, "-o", ref).returncode == 0
    ref_img = read_image(ref)
    sizes = {}
    for name, extra in (("m.spz", ()), ("m3.spz", ("--spz-version", "3")), ("m.splat", ()), ("m.glb", ()),
                        ("m.gltf", ())):
        out = tmp_path / name
        r = _mi_gs("export", TINY, "-o", out, *extra)
        assert r.returncode == 0, r.stderr
        info = json.loads(r.stdout)
        sizes[name] = info["bytes"]
        assert info["gaussians"] == 2000 and info["bytes"] == out.stat().st_size
        assert info.get("spz_version") == ({"m.spz": 4, "m3.spz": 3}.get(name))
        assert info.get("color_space") == ("srgb" if name.startswith("m.gl") else None)
    for name in ("m.spz", "m.splat", "m.glb"):
        img = tmp_path / f"{name}.exr"
        r = _mi_gs("render", tmp_path / name, "--camera", CAMERA, "-o", img)
        assert r.returncode == 0, r.stderr
        assert _psnr(read_image(img)[..., :3], ref_img[..., :3]) > (35.0 if name != "m.glb" else 60.0)
    for name, fmt, extra in (("m3.spz", "spz", {"version": 3}), ("m.gltf", "gltf", {"color_space": "srgb"})):
        r = _mi_gs("info", tmp_path / name)
        assert r.returncode == 0, r.stderr
        info = json.loads(r.stdout)
        assert info["format"] == fmt and info["gaussians"] == 2000 and info["sh_degree"] == 1
        assert extra.items() <= info.items()
    assert sizes["m.splat"] == 32 * 2000 and sizes["m.spz"] < sizes["m3.spz"] < sizes["m.splat"]
    assert sizes["m.gltf"] > 4 / 3 * sizes["m.glb"] - 2000          # (the buffer as base64)
    # back to .ply, fewer bands
    r = _mi_gs("export", tmp_path / "m.glb", "-o", tmp_path / "back.ply", "--sh-degree", "0")
    assert r.returncode == 0, r.stderr
    from mi_gaussians.model.gaussians import Gaussians

    assert Gaussians.load(tmp_path / "back.ply").sh_degree == 0
    (tmp_path / "bad.glb").write_bytes(b"glTF" + bytes(8))
    for args, words in (((tmp_path / "m.spz", "-o", tmp_path / "back.ply"), "--overwrite"),
                        ((TINY, "-o", tmp_path / "x.obj"), "unknown output format .obj (use .ply, .splat, .spz, .glb, "
                                                           ".gltf)"),
                        ((tmp_path / "nothing.ply", "-o", tmp_path / "y.spz"), "not found"),
                        ((TINY, "-o", tmp_path / "z.spz", "--sh-degree", "3"), "SH degree 1"),
                        ((tmp_path / "bad.glb", "-o", tmp_path / "z.spz"), "truncated GLB header")):
        r = _mi_gs("export", *args)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    for cmd in (("info", tmp_path / "bad.glb"), ("render", tmp_path / "bad.glb", "--camera", CAMERA, "-o",
                                                  tmp_path / "bad.exr")):
        r = _mi_gs(*cmd)
        assert r.returncode == 2 and f"{tmp_path / 'bad.glb'}: truncated GLB header" in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
