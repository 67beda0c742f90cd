"""Our exports against the ecosystem's own readers and writers, installed from the npm registry by the test set-up
(tests/js/package.json, pinned by tests/js/package-lock.json; ``npm ci`` runs once when tests/js/node_modules is
missing or older than the lock file):

* the Khronos glTF validator (``gltf-validator``) finds nothing in our .glb / .gltf but what it says of every
  KHR_gaussian_splatting file: its 2.0.0-dev.3.10 does not know the extension (one info) and so calls its attribute
  names invalid (one error each); a damaged copy shows that it checks the rest;
* three.js' GLTFLoader with its KHR_gaussian_splatting plugin (``three/addons``) loads our .glb in Node, and what it
  builds (centres, covariances, colours, packed SH; node transforms on others' files) is ours;
* PlayCanvas ``splat-transform`` reads our .spz (versions 4 and 3) and .splat into PLY, and its own .glb and .spz
  (4 and 3) load in ours, each compared with the source within the format's steps; ``mi-gs info`` and ``mi-gs render``
  take its files.

The browser (three.js' splat renderer in Chromium) is tests/test_export_browser.py.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mi_gaussians.model import frames
from mi_gaussians.model.ply import read_ply, write_ply
from mi_gaussians.model.web_formats import read_model_info, write_model
from test_gltf_export import assert_same_shapes, expected_scene, pack_glb, parse_glb, scene_of_two

ROOT = Path(__file__).resolve().parents[1]
JS = ROOT / "tests" / "js"
TINY = ROOT / "scenes" / "tiny_gaussians.ply"
CAMERA = ROOT / "scenes" / "tiny_gaussians_camera.json"
NPM_TIMEOUT = 600
GLTF_FROM_PLY = (-1.0, -1.0, 1.0)        # glTF's LUF from the PLY's RDF (a 180-degree turn about z), written out here
F = np.diag(GLTF_FROM_PLY)


@pytest.fixture(scope="session")
def js_tools() -> Path:
    """tests/js with its pinned npm packages installed (``npm ci``, once); skips only where node or npm is absent."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node and npm are not on this machine (Debian: apt-get install nodejs npm); the ecosystem's "
                    "readers and writers these tests run are npm packages")
    stamp = JS / "node_modules" / ".package-lock.json"
    if not stamp.is_file() or stamp.stat().st_mtime < (JS / "package-lock.json").stat().st_mtime:
        try:
            r = subprocess.run([npm, "ci", "--no-audit", "--no-fund", "--loglevel=error"], cwd=JS, capture_output=True,
                               text=True, timeout=NPM_TIMEOUT)
        except subprocess.TimeoutExpired:
            pytest.fail(f"npm ci in {JS} took over {NPM_TIMEOUT} s")
        if r.returncode != 0:
            pytest.fail(f"npm ci in {JS} failed: {r.stderr.strip()[-2000:]}")
    return JS


def node(*args, timeout: float = 120) -> str:
    r = subprocess.run(["node", *map(str, args)], cwd=JS, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout


def splat_transform(*args) -> None:
    node(JS / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs", "-q", "-w", *args)


def _model(n=400, degree=3, seed=0) -> dict:
    """Raw parameters in the ranges of a trained model (SH inside what 8-bit SH formats hold)."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return {"means": rng.uniform(-3, 3, (n, 3)).astype(np.float32),
            "scales": rng.uniform(-6, -1, (n, 3)).astype(np.float32),
            "rotations": rng.normal(size=(n, 4)).astype(np.float32),
            "opacities": rng.uniform(-4, 4, n).astype(np.float32),
            "sh_dc": rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32),
            "sh_rest": rng.uniform(-0.45, 0.45, (n, k, 3)).astype(np.float32)}


def _sig(x):
    return 1 / (1 + np.exp(-np.asarray(x, np.float64)))


def _cov(p) -> np.ndarray:
    a = frames.quat_to_matrix(p["rotations"]) * np.exp(np.asarray(p["scales"], np.float64))[:, None, :]
    return a @ np.transpose(a, (0, 2, 1))


def _matched(src: dict, got: dict) -> dict:
    """``src`` reordered as ``got`` (files may reorder Gaussians: .splat by importance), by nearest position."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(src["means"]).query(got["means"])
    assert len(set(idx.tolist())) == len(idx) and dist.max() < 1e-3, dist.max()
    return {k: np.asarray(v)[idx] for k, v in src.items()}


def assert_within_steps(got: dict, src: dict, fmt: str) -> None:
    """``got`` is ``src`` (matched by position) within the quantization steps of ``fmt`` (spz, splat, float)."""
    s = _matched(src, got)
    step = {"spz": dict(pos=0.5 / 4096, scale=0.5 / 16, alpha=0.5 / 255, dc=0.5 / (0.15 * 255), shape=0.1),
            "splat": dict(pos=0.0, scale=2e-6, alpha=0.5 / 255, dc=0.5 / 255 / 0.2820948, shape=0.06),
            "float": dict(pos=0.0, scale=2e-6, alpha=1e-6, dc=0.0, shape=1e-5)}[fmt]
    assert np.abs(got["means"] - s["means"]).max() <= step["pos"] + 1e-6
    assert np.abs(got["scales"] - s["scales"]).max() <= step["scale"] + 1e-6
    assert np.abs(_sig(got["opacities"]) - _sig(s["opacities"])).max() <= step["alpha"] + 1e-6
    dc_src = np.clip(s["sh_dc"], -0.5 / 0.2820948, 0.5 / 0.2820948) if fmt == "splat" else s["sh_dc"]
    assert np.abs(got["sh_dc"] - dc_src).max() <= step["dc"] + 1e-5
    assert_same_shapes(_cov(got), _cov(s), step["shape"])
    if fmt == "splat":
        assert got["sh_rest"].shape[1] == 0
        return
    rest = np.abs(np.asarray(got["sh_rest"]) - s["sh_rest"])
    if fmt == "spz":
        assert rest[:, :3].max() <= 4.5 / 128 + 1e-6 and rest[:, 3:].max() <= 8.5 / 128 + 1e-6
    else:
        assert rest.max() <= 1e-6


# ---------------------------------------------------------------------------------------------------- validator
def _validate(path: Path) -> dict:
    return json.loads(node("validate.mjs", path))


def test_gltf_validator_finds_nothing_but_the_unknown_extension(js_tools, tmp_path):
    for name, p, space in (("tiny.glb", read_ply(TINY), "srgb"), ("deg3.gltf", _model(), "linear"),
                           ("deg0.glb", _model(degree=0, seed=1), "srgb")):
        write_model(tmp_path / name, p, color_space=space)
        report = _validate(tmp_path / name)
        issues = report["issues"]
        ours = {a for a in parse_glb_or_gltf(tmp_path / name)[0]["meshes"][0]["primitives"][0]["attributes"]
                if a.startswith("KHR_gaussian_splatting:")}
        flagged = set()
        for m in issues["messages"]:
            if m["code"] == "UNSUPPORTED_EXTENSION":
                assert m["severity"] == 2 and m["pointer"] == "/extensionsUsed/0" and "KHR_gaussian_splatting" in m[
                    "message"], m
            else:
                assert m["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE", m
                flagged.add(m["pointer"].rsplit("/", 1)[1])
        assert flagged == ours and (issues["numWarnings"], issues["numInfos"], issues["numHints"]) == (0, 1, 0)
        assert issues["numErrors"] == len(ours) and report["info"]["totalVertexCount"] == len(p["means"])
    # the validator checks what it knows: a POSITION max that is not the data's is an error
    doc, binary = parse_glb((tmp_path / "tiny.glb").read_bytes())
    doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]["max"][1] += 0.5
    (tmp_path / "bad.glb").write_bytes(pack_glb(doc, binary))
    codes = {m["code"] for m in _validate(tmp_path / "bad.glb")["issues"]["messages"]}
    assert "ACCESSOR_MAX_MISMATCH" in codes


def parse_glb_or_gltf(path: Path) -> tuple[dict, bytes]:
    if path.suffix == ".glb":
        return parse_glb(path.read_bytes())
    import base64

    doc = json.loads(path.read_text())
    return doc, base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])


# ---------------------------------------------------------------------------------------------------- three.js
def _three(path: Path, out: Path) -> list[dict]:
    """What three.js' GLTFLoader (with GLTFGaussianSplatLoaderExtension) built from ``path``: per splat object its
    world matrix and its attributes as arrays."""
    node("three_load.mjs", path, out)
    splats = json.loads((out / "three.json").read_text())["splats"]
    for s in splats:
        s["matrixWorld"] = np.asarray(s["matrixWorld"], np.float64).reshape(4, 4).T     # (column-major)
        for name, a in s["attributes"].items():
            dtype = {"Float32Array": "<f4", "Uint8ClampedArray": "u1", "Uint32Array": "<u4"}[a["type"]]
            s[name] = np.fromfile(out / a["file"], dtype).reshape(a["count"], -1)
    return splats


def _three_sh(s: dict, degree: int) -> np.ndarray:
    """(N, K - 1, 3) SH coefficients of a three.js splat, unpacked from its clamped bytes ((b - 128) / 128)."""
    bands = []
    for l in range(1, degree + 1):
        b = s[f"sphericalHarmonics{l}"].view(np.uint8).reshape(len(s["position"]), -1)[:, :3 * (2 * l + 1)]
        bands.append((b.astype(np.float64) - 128) / 128)
    return np.concatenate(bands, axis=1).reshape(len(s["position"]), -1, 3)


def test_three_gltf_loader_reads_our_glb(js_tools, tmp_path):
    p = _model()
    write_model(tmp_path / "m.glb", p)
    (s,) = _three(tmp_path / "m.glb", tmp_path / "three")
    assert s["extension"]["colorSpace"] == "srgb_rec709_display"
    np.testing.assert_array_equal(s["matrixWorld"], np.eye(4))
    np.testing.assert_array_equal(s["position"], p["means"] * GLTF_FROM_PLY)
    cov = _cov(p)
    cov = F @ cov @ F
    got = s["covariance"]                                                    # xx, xy, xz, yy, yz, zz
    want = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], 1)
    assert np.abs(got - want).max(axis=1).max() <= 1e-5 * np.abs(want).max()
    rgb = np.clip(0.5 + 0.28209479177387814 * p["sh_dc"].astype(np.float64), 0, 1) * 255
    assert np.abs(s["color"][:, :3] - rgb).max() <= 0.5 + 1e-3
    assert np.abs(s["color"][:, 3] - 255 * _sig(p["opacities"])).max() <= 0.5 + 1e-3
    sh = p["sh_rest"] * frames.sh_flip_signs(GLTF_FROM_PLY)[:, None]       # the file's, as three reads them
    assert np.abs(_three_sh(s, 3) - sh).max() <= 0.5 / 128 + 1e-6


def test_three_gltf_loader_agrees_on_other_files_transforms(js_tools, tmp_path):
    """A file with node transforms, two primitives (one quantized) and a triangle mesh beside: three.js' world
    matrix applied to its centres and covariances, and its SH evaluated in the primitive's own frame, give what our
    reader gives in glTF's frame."""
    b, a, bq, m = scene_of_two()
    (tmp_path / "s.glb").write_bytes(b.glb())
    ours = frames.flip_axes(read_model_info(tmp_path / "s.glb")[0], GLTF_FROM_PLY)    # (back to glTF's frame)
    np.testing.assert_allclose(ours["means"], expected_scene(a, bq, m)["means"] * GLTF_FROM_PLY, atol=1e-5)
    splats = _three(tmp_path / "s.glb", tmp_path / "three")
    assert len(splats) == 2
    rng = np.random.default_rng(1)
    start = 0
    for s, degree in zip(splats, (2, 0)):
        n = len(s["position"])
        mw = s["matrixWorld"]
        np.testing.assert_allclose(mw, m, atol=1e-6)
        ref = {k: v[start:start + n] for k, v in ours.items()}
        np.testing.assert_allclose(s["position"] @ mw[:3, :3].T + mw[:3, 3], ref["means"], atol=1e-4)
        c = s["covariance"].astype(np.float64)
        local = np.stack([c[:, [0, 1, 2]], c[:, [1, 3, 4]], c[:, [2, 4, 5]]], axis=1)
        assert_same_shapes(mw[:3, :3] @ local @ mw[:3, :3].T, _cov(ref), 2e-3)
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rot = mw[:3, :3] / np.cbrt(np.linalg.det(mw[:3, :3]))
        three_c = np.einsum("nk,nkc->nc", frames.sh_basis(d @ rot, degree)[:, 1:], _three_sh(s, degree)) if degree \
            else np.zeros((n, 3))
        ours_c = np.einsum("nk,nkc->nc", frames.sh_basis(d, 2)[:, 1:], ref["sh_rest"])
        assert np.abs(three_c - ours_c).max() <= 0.03                        # (three's 8-bit SH)
        start += n


# ---------------------------------------------------------------------------------------------------- splat-transform
def test_splat_transform_reads_our_spz_and_splat(js_tools, tmp_path):
    p = _model(seed=2)
    for name, version, fmt in (("m4.spz", 4, "spz"), ("m3.spz", 3, "spz"), ("m.splat", 4, "splat")):
        write_model(tmp_path / name, p, spz_version=version)
        splat_transform(tmp_path / name, tmp_path / f"{name}.ply")
        assert_within_steps(read_ply(tmp_path / f"{name}.ply"), p, fmt)


def test_our_reader_reads_splat_transform_files(js_tools, tmp_path):
    p = _model(seed=3)
    write_ply(tmp_path / "src.ply", **p)
    for name, extra, fmt, meta in (("st.glb", (), "float", {"format": "glb", "color_space": "srgb"}),
                                   ("st4.spz", (), "spz", {"format": "spz", "version": 4}),
                                   ("st3.spz", ("--spz-version", "3"), "spz", {"format": "spz", "version": 3})):
        splat_transform(*extra, tmp_path / "src.ply", tmp_path / name)
        got, info = read_model_info(tmp_path / name)
        assert meta.items() <= info.items(), info
        assert_within_steps(got, p, fmt)
    assert info["antialiased"] is False and read_model_info(tmp_path / "st.glb")[1]["generator"].startswith(
        "splat-transform")


def test_mi_gs_info_and_render_take_splat_transform_files(js_tools, tmp_path):
    from mi_gaussians.data.images import read_image
    from test_cli import run

    for name in ("st.glb", "st.spz"):
        splat_transform(TINY, tmp_path / name)
    r = run("info", tmp_path / "st.glb")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["format"] == "glb" and info["gaussians"] == 2000 and info["sh_degree"] == 1
    assert info["generator"].startswith("splat-transform")
    images = {}
    for src in (TINY, tmp_path / "st.spz", tmp_path / "st.glb"):
        out = tmp_path / f"{src.name}.exr"
        r = run("render", src, "--camera", CAMERA, "-o", out)
        assert r.returncode == 0, r.stderr
        images[src.suffix] = read_image(out)[..., :3]

    def psnr(a, b):
        return 10 * math.log10(1 / np.mean((a - b) ** 2))

    assert psnr(images[".spz"], images[".ply"]) > 35 and psnr(images[".glb"], images[".ply"]) > 60
