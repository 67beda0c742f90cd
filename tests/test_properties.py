"""Property-based tests (Hypothesis) of every reader of user files: a 3DGS PLY, a COLMAP model (text and binary),
Blender / instant-ngp ``transforms*.json`` and the camera JSON of ``mi-gs render --camera``.

The property: whatever the bytes or the JSON, a reader either loads (and what it loads is valid: finite, with the
promised shapes) or raises a ``ValueError`` whose message is one line naming the file. Never another exception, a
traceback or a crash. Inputs come both from raw bytes / arbitrary JSON and from valid files with a few tokens, bytes
or values replaced, which reach the checks deep inside a reader. Hypothesis runs derandomized (the same examples on
every run), so the tests cannot fail only sometimes.
"""

from __future__ import annotations

import json
import math
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from mi_gaussians.data.camera import Camera
from mi_gaussians.data.colmap import read_model
from mi_gaussians.data.dataset import load_dataset
from mi_gaussians.model.ply import ply_property_names, read_ply, write_ply

DATA = Path(__file__).parent / "data"
SETTINGS = settings(max_examples=150, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("properties")


def assert_one_line_error(e: ValueError, path) -> None:
    event("refused")
    msg = str(e)
    assert "\n" not in msg and "\r" not in msg, repr(msg)
    assert msg.startswith(str(path)), (msg, str(path))


# ---------------------------------------------------------------------------------------------------- generators
JSON_SCALARS = st.none() | st.booleans() | st.integers(-10**20, 10**20) | \
    st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=12)
ANY_JSON = st.recursive(JSON_SCALARS, lambda children: st.lists(children, max_size=5)
                        | st.dictionaries(st.text(max_size=8), children, max_size=5), max_leaves=30)
NUMBER_LIKE = st.floats(allow_nan=True, allow_infinity=True) | st.integers(-10**6, 10**6) | st.booleans() | \
    st.none() | st.text(max_size=6) | st.lists(st.floats(-5, 5), max_size=5)


def mostly(valid, noise):
    """``valid`` about three times in four, else ``noise``."""
    return st.integers(0, 3).flatmap(lambda k: valid if k < 3 else noise)


def mutate_tokens(text: str, data) -> str:
    """``text`` with 1-4 whitespace-separated tokens replaced, removed or duplicated."""
    lines = [ln.split(" ") for ln in text.splitlines()]
    for _ in range(data.draw(st.integers(1, 4), "edits")):
        i = data.draw(st.integers(0, len(lines) - 1), "line")
        if not lines[i]:
            continue
        j = data.draw(st.integers(0, len(lines[i]) - 1), "token")
        op = data.draw(st.sampled_from(["replace", "remove", "duplicate", "drop line"]), "op")
        if op == "replace":
            lines[i][j] = data.draw(st.sampled_from(["", "-1", "0", "nan", "inf", "1e400", "x", "9" * 30, "#",
                                                     "PINHOLE", "OPENCV_FISHEYE", "3.5", "-0", "\t"]), "token value")
        elif op == "remove":
            del lines[i][j]
        elif op == "duplicate":
            lines[i].insert(j, lines[i][j])
        else:
            del lines[i]
            if not lines:
                return ""
    return "\n".join(" ".join(t) for t in lines) + "\n"


def mutate_bytes(data_bytes: bytes, data) -> bytes:
    """``data_bytes`` with a few bytes overwritten, a cut, or inserted bytes."""
    b = bytearray(data_bytes)
    for _ in range(data.draw(st.integers(1, 3), "edits")):
        op = data.draw(st.sampled_from(["set", "truncate", "insert"]), "op")
        pos = data.draw(st.integers(0, max(0, len(b) - 1)), "position")
        if op == "set" and b:
            b[pos] = data.draw(st.integers(0, 255), "byte")
        elif op == "truncate":
            del b[pos:]
        else:
            b[pos:pos] = data.draw(st.binary(min_size=1, max_size=16), "inserted")
    return bytes(b)


# ---------------------------------------------------------------------------------------------------- PLY
def _valid_ply(tmp: Path, degree: int, n: int, fmt: str) -> bytes:
    rng = np.random.default_rng(n)
    k = (degree + 1) ** 2 - 1
    p = tmp / "valid.ply"
    write_ply(p, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(size=n),
              rng.normal(size=(n, 3)), rng.normal(size=(n, k, 3)))
    if fmt == "binary_little_endian":
        return p.read_bytes()
    names = ply_property_names(degree)
    raw = p.read_bytes()
    body = np.frombuffer(raw[raw.index(b"end_header\n") + 11:], "<f4").reshape(n, len(names))
    header = raw[:raw.index(b"end_header\n")].decode().replace("binary_little_endian", fmt) + "end_header\n"
    if fmt == "ascii":
        return header.encode() + "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in body).encode()
    return header.encode() + body.astype(">f4").tobytes()


def load_or_refused(loader, path: Path):
    """``loader(path)``, or None when it was refused with a one-line ValueError naming ``path`` (the only other
    outcome allowed); records which of the two happened."""
    try:
        result = loader(path)
    except ValueError as e:
        assert_one_line_error(e, path)
        return None
    event("loaded")
    return result


def check_ply(path: Path) -> None:
    d = load_or_refused(read_ply, path)
    if d is None:
        return
    n = d["means"].shape[0]
    assert d["scales"].shape == (n, 3) and d["rotations"].shape == (n, 4) and d["opacities"].shape == (n,)
    assert d["sh_dc"].shape == (n, 3) and d["sh_rest"].shape[0] == n and d["sh_rest"].shape[1] in (0, 3, 8, 15)
    assert all(np.all(np.isfinite(v)) and v.dtype == np.float32 for v in d.values())


@SETTINGS
@given(raw=st.binary(max_size=600))
def test_ply_arbitrary_bytes(work, raw):
    p = work / "any.ply"
    p.write_bytes(raw)
    check_ply(p)


@SETTINGS
@given(raw=st.binary(max_size=400) | st.binary(min_size=204, max_size=204))    # 204: three vertices of 17 floats
def test_ply_header_then_arbitrary_bytes(work, raw):
    head = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n" + \
        b"".join(f"property float {n}\n".encode() for n in ply_property_names(0)) + b"end_header\n"
    p = work / "head.ply"
    p.write_bytes(head + raw)
    check_ply(p)


@SETTINGS
@given(degree=st.integers(0, 3), n=st.integers(0, 4),
       fmt=st.sampled_from(["binary_little_endian", "binary_big_endian", "ascii"]), data=st.data())
def test_ply_mutated_valid_file(work, degree, n, fmt, data):
    good = _valid_ply(work, degree, n, fmt)
    header_end = good.index(b"end_header") + 11
    if data.draw(st.booleans(), "edit the header as text"):
        raw = mutate_tokens(good[:header_end].decode(), data).encode() + good[header_end:]
    else:
        raw = mutate_bytes(good, data)
    p = work / "mutated.ply"
    p.write_bytes(raw)
    check_ply(p)


# ---------------------------------------------------------------------------------------------------- COLMAP
@pytest.fixture(scope="module")
def colmap_models(work) -> dict[str, dict[str, bytes]]:
    """The tiny fixture's three files as text and as binary (written by pycolmap)."""
    import pycolmap

    text_dir = DATA / "tiny_colmap" / "sparse" / "0"
    bin_dir = work / "colmap_bin"
    bin_dir.mkdir()
    pycolmap.Reconstruction(str(text_dir)).write_binary(str(bin_dir))
    return {ext: {s: (d / f"{s}{ext}").read_bytes() for s in ("cameras", "images", "points3D")}
            for ext, d in ((".txt", text_dir), (".bin", bin_dir))}


def check_colmap(model_dir: Path) -> None:
    m = load_or_refused(read_model, model_dir)
    if m is None:
        return
    assert m.images and all(i.camera_id in m.cameras for i in m.images)
    for im in m.images:
        r = im.world_to_camera[:3, :3]
        assert np.all(np.isfinite(im.world_to_camera)) and np.allclose(r @ r.T, np.eye(3), atol=1e-6)
    for c in m.cameras.values():
        assert c.width > 0 and c.height > 0 and all(math.isfinite(p) for p in c.params)
    assert np.all(np.isfinite(m.points_xyz)) and m.points_xyz.shape == m.points_rgb.shape
    assert np.all((m.points_rgb >= 0) & (m.points_rgb <= 1))


def _write_model(work: Path, name: str, files: dict[str, bytes], ext: str) -> Path:
    d = work / name
    if d.exists():
        shutil.rmtree(d)
    d.mkdir()
    for stem, b in files.items():
        (d / f"{stem}{ext}").write_bytes(b)
    return d


@SETTINGS
@given(ext=st.sampled_from([".txt", ".bin"]), stem=st.sampled_from(["cameras", "images", "points3D"]),
       raw=st.binary(max_size=400))
def test_colmap_arbitrary_bytes(work, colmap_models, ext, stem, raw):
    files = dict(colmap_models[ext], **{stem: raw})
    check_colmap(_write_model(work, "colmap_any", files, ext))


@SETTINGS
@given(ext=st.sampled_from([".txt", ".bin"]), stem=st.sampled_from(["cameras", "images", "points3D"]),
       data=st.data())
def test_colmap_mutated_valid_model(work, colmap_models, ext, stem, data):
    good = colmap_models[ext][stem]
    bad = mutate_tokens(good.decode(), data).encode() if ext == ".txt" else mutate_bytes(good, data)
    files = dict(colmap_models[ext], **{stem: bad})
    check_colmap(_write_model(work, "colmap_mutated", files, ext))


@SETTINGS
@given(values=st.lists(st.integers(0, 2**64 - 1), min_size=1, max_size=4), position=st.integers(0, 200))
def test_colmap_binary_huge_counts(work, colmap_models, values, position):
    """Counts and lengths overwritten by huge integers are refused before anything is allocated."""
    for stem in ("cameras", "images", "points3D"):
        b = bytearray(colmap_models[".bin"][stem])
        pos = min(position, max(0, len(b) - 8)) // 8 * 8
        for i, v in enumerate(values):
            if pos + 8 * (i + 1) <= len(b):
                b[pos + 8 * i: pos + 8 * (i + 1)] = struct.pack("<Q", v)
        check_colmap(_write_model(work, "colmap_counts", dict(colmap_models[".bin"], **{stem: bytes(b)}), ".bin"))


# ---------------------------------------------------------------------------------------------------- transforms
def check_dataset(root: Path, doc) -> None:
    """Load ``root``: a dataset or one line naming a file (under ``root``, or an image path the json gives)."""
    try:
        ds = load_dataset(root, test_every=0)
    except ValueError as e:
        msg = str(e)
        assert "\n" not in msg, repr(msg)
        frames = doc.get("frames") if isinstance(doc, dict) else None
        named = [f["file_path"] for f in frames if isinstance(f, dict) and isinstance(f.get("file_path"), str)] \
            if isinstance(frames, list) else []
        assert any(msg.startswith(p) for p in [str(root)] + [n for n in named if n.startswith("/")]), msg
        event("refused")
        return
    event("loaded")
    assert ds.train
    for v in ds.train + ds.test:
        c = v.camera
        assert c.width >= 1 and c.height >= 1 and np.all(np.isfinite(c.world_to_camera))
        assert all(math.isfinite(x) and x > 0 for x in (c.fx, c.fy))


def _frame_strategy(names):
    matrix = st.lists(st.lists(st.floats(-3, 3) | NUMBER_LIKE, min_size=3, max_size=5), min_size=3, max_size=5)
    rigid = st.sampled_from([[[1.0, 0, 0, 0.5], [0, 1.0, 0, 0], [0, 0, 1.0, 3.0], [0, 0, 0, 1.0]],
                             [[0.0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, -2.5]]])
    return st.fixed_dictionaries(
        {"file_path": mostly(st.sampled_from(names), st.text(max_size=10) | NUMBER_LIKE),
         "transform_matrix": mostly(rigid, matrix | NUMBER_LIKE)},
        optional={"fl_x": st.floats(1, 50) | NUMBER_LIKE, "w": st.integers(-2, 40) | NUMBER_LIKE,
                  "h": st.integers(-2, 40) | NUMBER_LIKE, "k1": st.floats(-1, 1) | NUMBER_LIKE,
                  "camera_model": st.sampled_from(["OPENCV", "PINHOLE", "OPENCV_FISHEYE"]) | NUMBER_LIKE})


def _transforms_strategy(names):
    meta = st.fixed_dictionaries({"camera_angle_x": mostly(st.floats(0.1, 1.5), NUMBER_LIKE)}, optional={
        "fl_x": st.floats(1, 50) | NUMBER_LIKE, "fl_y": NUMBER_LIKE, "cx": NUMBER_LIKE, "cy": NUMBER_LIKE,
        "w": st.integers(-2, 40) | NUMBER_LIKE, "h": st.integers(-2, 40) | NUMBER_LIKE, "k1": NUMBER_LIKE,
        "k3": NUMBER_LIKE, "k4": NUMBER_LIKE, "is_fisheye": st.booleans() | NUMBER_LIKE})
    frames = mostly(st.lists(_frame_strategy(names), min_size=1, max_size=3), NUMBER_LIKE)
    return mostly(st.builds(lambda m, f: dict(m, frames=f), meta, frames), ANY_JSON)


@pytest.fixture(scope="module")
def blender_root(work) -> Path:
    root = work / "blender"
    shutil.copytree(DATA / "tiny_blender", root)
    return root


@pytest.fixture(scope="module")
def ngp_root(work) -> Path:
    root = work / "ngp"
    shutil.copytree(DATA / "tiny_ngp", root)
    return root


@SETTINGS
@given(doc=_transforms_strategy(["train/r_0", "train/r_1", "./train/r_1.png", "../x", "train\0r", "a" * 300]))
def test_blender_transforms_arbitrary_json(blender_root, doc):
    p = blender_root / "transforms_train.json"
    p.write_text(json.dumps(doc))
    check_dataset(blender_root, doc)


@SETTINGS
@given(doc=_transforms_strategy(["images/0000.png", "images/0001.png", "images/0000", "/etc/passwd", "\0"]))
def test_ngp_transforms_arbitrary_json(ngp_root, doc):
    p = ngp_root / "transforms.json"
    p.write_text(json.dumps(doc))
    check_dataset(ngp_root, doc)


@SETTINGS
@given(raw=st.binary(max_size=300))
def test_transforms_arbitrary_bytes(blender_root, raw):
    p = blender_root / "transforms_train.json"
    p.write_bytes(raw)
    check_dataset(blender_root, None)


# ---------------------------------------------------------------------------------------------------- camera JSON
def _rigid(q, t, perturb):
    """A world-to-camera matrix from a quaternion and a translation, optionally made not rigid (scaled, sheared,
    mirrored, a wrong last row)."""
    from mi_gaussians.data.colmap import quaternion_to_matrix

    q = np.asarray(q, np.float64)
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(q / np.linalg.norm(q)) if np.linalg.norm(q) > 1e-3 else np.eye(3)
    m[:3, 3] = t
    if perturb == "scale":
        m[:3, :3] *= 1.01
    elif perturb == "shear":
        m[0, 1] += 0.05
    elif perturb == "mirror":
        m[:3, 0] *= -1
    elif perturb == "last row":
        m[3, 0] = 0.5
    return m.tolist()


RIGID = st.builds(_rigid, st.lists(st.floats(-1, 1), min_size=4, max_size=4), st.lists(st.floats(-5, 5), min_size=3,
                                                                                        max_size=3),
                  mostly(st.just(None), st.sampled_from(["scale", "shear", "mirror", "last row"])))
CAMERA_FIELDS = {"width": mostly(st.integers(1, 5000), st.integers(-2, 0) | st.floats(1, 9) | NUMBER_LIKE),
                 "height": mostly(st.integers(1, 5000), st.integers(-2, 0) | st.floats(1, 9) | NUMBER_LIKE),
                 "fx": mostly(st.floats(0.1, 100), NUMBER_LIKE), "fy": mostly(st.floats(0.1, 100), NUMBER_LIKE),
                 "cx": mostly(st.floats(-10, 100), NUMBER_LIKE), "cy": mostly(st.floats(-10, 100), NUMBER_LIKE),
                 "world_to_camera": mostly(RIGID, st.lists(st.lists(st.floats(-2, 2), min_size=4, max_size=4),
                                                           min_size=4, max_size=4)
                                           | st.lists(st.lists(st.floats(-2, 2) | NUMBER_LIKE, min_size=3, max_size=5),
                                                      min_size=3, max_size=5) | NUMBER_LIKE)}


@SETTINGS
@given(doc=mostly(st.fixed_dictionaries(CAMERA_FIELDS, optional={"name": NUMBER_LIKE}),
                  st.fixed_dictionaries({}, optional=CAMERA_FIELDS) | ANY_JSON))
def test_camera_json_arbitrary(work, doc):
    p = work / "camera.json"
    p.write_text(json.dumps(doc))
    c = load_or_refused(Camera.from_json, p)
    if c is None:
        return
    event("accepted")
    assert isinstance(c.width, int) and isinstance(c.height, int) and c.width >= 1 and c.height >= 1
    assert c.width == doc["width"] and c.height == doc["height"]          # (never rounded: 12.5 is refused)
    assert all(math.isfinite(x) for x in (c.fx, c.fy, c.cx, c.cy)) and c.fx > 0 and c.fy > 0
    assert np.all(np.isfinite(c.world_to_camera)) and c.world_to_camera.shape == (4, 4)
    r = c.world_to_camera[:3, :3]                                          # a rigid camera, nothing else
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-4) and abs(np.linalg.det(r) - 1) < 1e-4
    assert np.allclose(c.world_to_camera[3], [0, 0, 0, 1])


# ---------------------------------------------------------------------------------------------------- config.json
def _field_values(value):
    """Values for one setting: mostly its own type (the default, or another of the kind), else arbitrary JSON."""
    if isinstance(value, bool):
        valid = st.booleans()
    elif isinstance(value, int):
        valid = st.integers(-3, 40_000)
    elif isinstance(value, float):
        valid = st.floats(-1, 10, allow_nan=False)
    elif isinstance(value, str):
        valid = st.sampled_from([value, "default", "mcmc", "cube", "frustum", "auto", "shapes", "nope"])
    elif isinstance(value, (tuple, list)):
        valid = st.lists(st.floats(0, 1) | st.integers(0, 9000), max_size=4)
    else:
        valid = st.none() | st.integers(16, 600)
    return mostly(st.just(value) | valid, ANY_JSON)


def _config_docs():
    from mi_gaussians.config import TrainConfig

    base = TrainConfig().to_dict()
    return st.fixed_dictionaries({}, optional={
        k: (st.fixed_dictionaries({}, optional={f: _field_values(v) for f, v in sub.items()}) | ANY_JSON)
        if isinstance(sub, dict) else _field_values(sub) for k, sub in base.items()})


@SETTINGS
@given(doc=_config_docs())
def test_config_json_arbitrary(work, doc):
    """A hand-edited config.json: every field any JSON value. It is read as exactly what it says (each value of its
    field's type and in its range, nothing converted: "false" is not true, 300.0 not 300) or refused in one line
    naming the file and the key; never a traceback."""
    from mi_gaussians.config import TrainConfig
    from mi_gaussians.run_folder import RunRecord

    folder = work / "record"
    folder.mkdir(exist_ok=True)
    (folder / "config.json").write_text(json.dumps({"dataset": "/data", "train": doc}))
    try:
        record = RunRecord.read(folder, "missing")
    except ValueError as e:
        assert_one_line_error(e, folder / "config.json")
        assert "key " in str(e) or "training settings" in str(e), str(e)
        return
    event("accepted")
    got = json.loads(json.dumps(record.train.to_dict()))
    want = json.loads(json.dumps(TrainConfig().to_dict()))
    for k, v in doc.items():
        if isinstance(v, dict):
            want[k].update(v)
        else:
            want[k] = v
    dens = doc.get("densify")
    if isinstance(dens, dict) and "opacity_reset_interval" in dens and "prune_large_after" not in dens:
        # (read as a record from before prune_large_after: its large-Gaussian prunes began after the first reset)
        want["densify"]["prune_large_after"] = dens["opacity_reset_interval"]
    if isinstance(doc.get("data"), dict) and "extent" not in doc["data"]:
        want["data"]["extent"] = "cameras"      # (a record from before data.extent: lengths of the cameras' spread)
    assert got == json.loads(json.dumps(want)) and record.train.validate() is record.train
