"""3DGS PLY reading / writing: bit-exact round trips, files by other tools, malformed files, Mitsuba's ellipsoids."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np
import pytest

import mitsuba as mi

from mi_gaussians import conventions as cv
from mi_gaussians.model.gaussians import Gaussians
from mi_gaussians.model.ply import (
    PLYError,
    convert_ply,
    ply_property_names,
    read_ply,
    read_ply_header,
    write_ply,
)

DATA = Path(__file__).parent / "data" / "ply"
KEYS = ("means", "scales", "rotations", "opacities", "sh_dc", "sh_rest")


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    mi.set_variant(variant)     # (test_plugins switches variants: start each module on the run's own)


def random_arrays(n: int, degree: int, seed: int = 0, odd: bool = True) -> dict[str, np.ndarray]:
    """Random raw parameters; with ``odd`` the first values are -0.0, denormals, huge and tiny numbers."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    a = {
        "means": rng.normal(size=(n, 3)),
        "scales": rng.normal(size=(n, 3)) - 3.0,
        "rotations": rng.normal(size=(n, 4)),
        "opacities": rng.normal(size=n) * 3.0,
        "sh_dc": rng.normal(size=(n, 3)),
        "sh_rest": rng.normal(size=(n, k, 3)) * 0.1,
    }
    a = {key: v.astype(np.float32) for key, v in a.items()}
    if odd:
        specials = np.array([-0.0, 1e-45, -1e-45, 1.1754942e-38, -3e-39, 3.4028235e38, -3.4028235e38, 1e-30,
                             np.float32(0.1), 16777217.0], dtype=np.float32)
        for key, v in a.items():
            flat = v.reshape(-1)
            m = min(flat.size, specials.size)
            flat[:m] = specials[:m]
    return a


def assert_bits_equal(a: np.ndarray, b: np.ndarray):
    assert a.dtype == np.float32 and b.dtype == np.float32
    assert a.shape == b.shape
    assert a.tobytes() == b.tobytes()


def raw_ply(names, rows, fmt="binary_little_endian", types=None, comments=(), newline="\n",
            before=(), after=()) -> bytes:
    """A PLY file built without ply.py: ``names`` with PLY type names ``types`` (default float), ``rows`` (N, P)."""
    types = types or ["float"] * len(names)
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, len(names))
    lines = ["ply", f"format {fmt} 1.0"] + [f"comment {c}" for c in comments]
    for el_name, el_count, el_props, _ in before:
        lines.append(f"element {el_name} {el_count}")
        lines += [f"property {p}" for p in el_props]
    lines.append(f"element vertex {rows.shape[0]}")
    lines += [f"property {t} {n}" for t, n in zip(types, names)]
    for el_name, el_count, el_props, _ in after:
        lines.append(f"element {el_name} {el_count}")
        lines += [f"property {p}" for p in el_props]
    lines.append("end_header")
    header = (newline.join(lines) + newline).encode("utf-8")
    codes = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "uint8": "u1",
             "int": "i4", "short": "i2", "half": "f2", "ushort": "u2", "char": "i1", "uint": "u4"}
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) if codes[t][0] == "f" else str(int(v)) for v, t in zip(r, types))
                       + "\n" for r in rows).encode("ascii")
        pre = b"".join(p[3] for p in before)
        post = b"".join(p[3] for p in after)
        return header + pre + body + post
    bo = "<" if fmt == "binary_little_endian" else ">"
    dt = np.dtype([(n, bo + codes[t]) for n, t in zip(names, types)])
    rec = np.empty(rows.shape[0], dt)
    for j, n in enumerate(names):
        rec[n] = rows[:, j]
    return header + b"".join(p[3] for p in before) + rec.tobytes() + b"".join(p[3] for p in after)


def table_of(a: dict, names: list[str]) -> np.ndarray:
    """Rows (N, P) of the arrays ``a`` for PLY property ``names`` (any order), via an explicit index formula."""
    n = a["means"].shape[0]
    k = a["sh_rest"].shape[1]
    cols = {"x": a["means"][:, 0], "y": a["means"][:, 1], "z": a["means"][:, 2], "opacity": a["opacities"]}
    for i in range(3):
        cols[f"f_dc_{i}"] = a["sh_dc"][:, i]
        cols[f"scale_{i}"] = a["scales"][:, i]
    for i in range(4):
        cols[f"rot_{i}"] = a["rotations"][:, i]
    for c in range(3):          # channel-major: f_rest_{c * k + j} is coefficient j of channel c
        for j in range(k):
            cols[f"f_rest_{c * k + j}"] = a["sh_rest"][:, j, c]
    return np.stack([cols.get(nm, np.zeros(n, np.float32)) for nm in names], axis=1)


def one_line_error(excinfo, path, *words):
    msg = str(excinfo.value)
    assert isinstance(excinfo.value, ValueError)
    assert "\n" not in msg and "\r" not in msg
    assert str(path) in msg
    for w in words:
        assert w in msg, msg
    return msg


# ---------------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_bit_exact(tmp_path, degree):
    a = random_arrays(37, degree, seed=degree)
    path = tmp_path / f"g{degree}.ply"
    write_ply(path, **a)
    b = read_ply(path)
    assert set(b) == set(KEYS)
    for key in KEYS:
        assert_bits_equal(a[key], b[key])
        assert b[key].flags.c_contiguous
    # writing what we read gives the same file, byte for byte
    write_ply(tmp_path / "again.ply", **b)
    assert (tmp_path / "again.ply").read_bytes() == path.read_bytes()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_file_layout_matches_reference(tmp_path, degree):
    a = random_arrays(5, degree, seed=10 + degree, odd=False)
    path = tmp_path / "layout.ply"
    write_ply(path, **a)
    names = ply_property_names(degree)
    assert len(names) == 17 + 3 * ((degree + 1) ** 2 - 1)
    expected_header = ("ply\nformat binary_little_endian 1.0\nelement vertex 5\n"
                       + "".join(f"property float {n}\n" for n in names) + "end_header\n").encode()
    data = path.read_bytes()
    assert data.startswith(expected_header)
    body = np.frombuffer(data[len(expected_header):], dtype="<f4").reshape(5, len(names))
    assert np.array_equal(body, table_of(a, names))
    assert np.all(body[:, 3:6] == 0.0)  # normals are zero


def test_header_is_byte_exact_copy_of_reference_layout(tmp_path):
    ref_header = (DATA / "reference_3dgs_sh3_header.txt").read_bytes()
    a = random_arrays(2, 3, seed=5)
    path = tmp_path / "ours.ply"
    write_ply(path, **a)
    assert path.read_bytes()[: len(ref_header)] == ref_header
    # a file with the reference header and hand-packed records reads back as expected
    names = [ln.split()[-1] for ln in ref_header.decode().splitlines() if ln.startswith("property")]
    rows = np.arange(2 * 62, dtype=np.float32).reshape(2, 62) * 0.5 - 7.0
    ref = tmp_path / "ref.ply"
    ref.write_bytes(ref_header + b"".join(struct.pack("<62f", *r) for r in rows))
    b = read_ply(ref)
    idx = {n: i for i, n in enumerate(names)}
    assert np.array_equal(b["means"], rows[:, [idx["x"], idx["y"], idx["z"]]])
    assert np.array_equal(b["opacities"], rows[:, idx["opacity"]])
    assert np.array_equal(b["rotations"], rows[:, [idx[f"rot_{i}"] for i in range(4)]])
    # channel-major f_rest: R coefficients are f_rest_0..14, G 15..29, B 30..44
    for j in range(15):
        for c in range(3):
            assert b["sh_rest"][0, j, c] == rows[0, idx[f"f_rest_{c * 15 + j}"]]


def test_gaussians_save_load_round_trip(tmp_path):
    a = random_arrays(11, 2, seed=3)
    for k in ("sh_dc", "sh_rest"):      # a model to render: no colour beyond MAX_ABS_SH_COEFFICIENT (tested below)
        a[k] = np.where(np.abs(a[k]) > cv.MAX_ABS_SH_COEFFICIENT, np.float32(2.5), a[k])
    g = Gaussians.from_numpy(**a)
    g.save_ply(tmp_path / "g.ply")
    h = Gaussians.load_ply(tmp_path / "g.ply")
    assert h.sh_degree == 2 and h.n == 11
    for key, v in h.numpy().items():
        assert_bits_equal(a[key], v)


def test_empty_model_round_trip(tmp_path):
    a = random_arrays(0, 1, odd=False)
    write_ply(tmp_path / "e.ply", **a)
    b = read_ply(tmp_path / "e.ply")
    assert b["means"].shape == (0, 3) and b["sh_rest"].shape == (0, 3, 3)
    g = Gaussians.load_ply(tmp_path / "e.ply")
    assert g.n == 0 and g.sh_degree == 1
    g.save_ply(tmp_path / "e2.ply")
    assert (tmp_path / "e2.ply").read_bytes() == (tmp_path / "e.ply").read_bytes()


def test_write_is_atomic_and_overwrites(tmp_path):
    path = tmp_path / "sub" / "m.ply"
    write_ply(path, **random_arrays(3, 0))
    write_ply(path, **random_arrays(4, 1))
    assert read_ply(path)["means"].shape == (4, 3)
    assert sorted(os.listdir(path.parent)) == ["m.ply"]  # no temporary files left behind
    bad = random_arrays(4, 1)
    bad["opacities"][2] = np.nan
    with pytest.raises(PLYError) as ei:
        write_ply(path, **bad)
    one_line_error(ei, path, "non-finite", "opacities")
    assert read_ply(path)["means"].shape == (4, 3)  # the old file is untouched
    assert sorted(os.listdir(path.parent)) == ["m.ply"]


def test_write_rejects_bad_shapes(tmp_path):
    a = random_arrays(4, 1)
    with pytest.raises(ValueError, match="sh_rest"):
        write_ply(tmp_path / "x.ply", **{**a, "sh_rest": np.zeros((4, 5, 3), np.float32)})
    with pytest.raises(ValueError, match="rotations"):
        write_ply(tmp_path / "x.ply", **{**a, "rotations": np.zeros((4, 3), np.float32)})
    assert not (tmp_path / "x.ply").exists()


def test_f_rest_counts():
    assert [sum(n.startswith("f_rest_") for n in ply_property_names(d)) for d in range(4)] == [0, 9, 24, 45]
    with pytest.raises(ValueError):
        ply_property_names(4)


# ---------------------------------------------------------------------------------------------------- other tools
def supersplat_like(a: dict, rng) -> tuple[list[str], list[str], np.ndarray]:
    """Shuffled property order, no normals, extra properties of several types."""
    degree_names = [n for n in ply_property_names(3 if a["sh_rest"].shape[1] == 15 else 1) if n not in ("nx", "ny", "nz")]
    names = list(degree_names) + ["red", "green", "blue", "extra_double", "segment_id"]
    types = ["float"] * len(degree_names) + ["uchar", "uchar", "uchar", "double", "int"]
    perm = rng.permutation(len(names))
    names = [names[i] for i in perm]
    types = [types[i] for i in perm]
    n = a["means"].shape[0]
    rows = table_of(a, names).astype(np.float64)
    for j, nm in enumerate(names):
        if nm in ("red", "green", "blue"):
            rows[:, j] = rng.integers(0, 256, n)
        elif nm == "extra_double":
            rows[:, j] = rng.normal(size=n) * 1e300
        elif nm == "segment_id":
            rows[:, j] = rng.integers(-5, 5, n)
    return names, types, rows


@pytest.mark.parametrize("degree", [1, 3])
def test_supersplat_like_export(tmp_path, degree):
    rng = np.random.default_rng(degree)
    a = random_arrays(9, degree, seed=20 + degree, odd=False)
    names, types, rows = supersplat_like(a, rng)
    path = tmp_path / "supersplat.ply"
    path.write_bytes(raw_ply(names, rows, types=types, comments=["Exported from SuperSplat", "caf\u00e9 \u2013 UTF-8"],
                             newline="\r\n", after=[("chunk_info", 1, ["float a", "float b"], b"\0" * 8)]))
    b = read_ply(path)
    for key in KEYS:
        assert_bits_equal(a[key], b[key])


def test_double_half_bigendian_ascii(tmp_path):
    a = random_arrays(6, 1, seed=7, odd=False)
    names = ply_property_names(1)
    rows = table_of(a, names)
    # double: values are exactly representable, so conversion back to float32 is exact
    p = tmp_path / "double.ply"
    p.write_bytes(raw_ply(names, rows, types=["double"] * len(names)))
    for key, v in read_ply(p).items():
        assert_bits_equal(a[key], v)
    # big-endian float32
    p = tmp_path / "be.ply"
    p.write_bytes(raw_ply(names, rows, fmt="binary_big_endian"))
    for key, v in read_ply(p).items():
        assert_bits_equal(a[key], v)
    # half precision: values rounded to half first
    p = tmp_path / "half.ply"
    p.write_bytes(raw_ply(names, rows, types=["half"] * len(names)))
    for key, v in read_ply(p).items():
        assert np.array_equal(v, a[key].astype(np.float16).astype(np.float32))
    # ascii (repr of the float32 value as a double round-trips exactly), with a list element before the vertices
    p = tmp_path / "ascii.ply"
    p.write_bytes(raw_ply(names, rows, fmt="ascii",
                          before=[("face", 2, ["list uchar int vertex_indices"], b"3 0 1 2\n4 0 1 2 3\n")]))
    for key, v in read_ply(p).items():
        assert_bits_equal(a[key], v)


def test_fixed_size_element_before_vertex(tmp_path):
    a = random_arrays(4, 0, seed=8, odd=False)
    names = ply_property_names(0)
    camera = np.array([1.5, 2.5], "<f4").tobytes() + b"\x07"
    p = tmp_path / "pre.ply"
    p.write_bytes(raw_ply(names, table_of(a, names),
                          before=[("camera", 1, ["float fx", "float fy", "uchar id"], camera)]))
    for key, v in read_ply(p).items():
        assert_bits_equal(a[key], v)
    assert [e.name for e in read_ply_header(p).elements] == ["camera", "vertex"]


# ---------------------------------------------------------------------------------------------------- malformed files
def write_good(tmp_path, name="m.ply", n=5, degree=1):
    p = tmp_path / name
    write_ply(p, **random_arrays(n, degree, odd=False))
    return p


def test_missing_attribute(tmp_path):
    a = random_arrays(3, 1, odd=False)
    names = [n for n in ply_property_names(1) if n not in ("opacity", "rot_2")]
    p = tmp_path / "missing.ply"
    p.write_bytes(raw_ply(names, table_of(a, names)))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "missing", "'opacity'", "'rot_2'")


def test_truncated_file(tmp_path):
    p = write_good(tmp_path)
    data = p.read_bytes()
    p.write_bytes(data[:-10])
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "truncated")


def test_count_larger_than_data(tmp_path):
    p = write_good(tmp_path, n=5)
    p.write_bytes(p.read_bytes().replace(b"element vertex 5\n", b"element vertex 6\n", 1))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "truncated", "6 vertices")


def test_count_smaller_than_data(tmp_path):
    p = write_good(tmp_path, n=5)
    p.write_bytes(p.read_bytes().replace(b"element vertex 5\n", b"element vertex 4\n", 1))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "vertex count mismatch", "4 vertices")


@pytest.mark.parametrize("bad,word", [(np.nan, "NaN"), (np.inf, "Inf"), (-np.inf, "Inf")])
def test_nonfinite_values(tmp_path, bad, word):
    a = random_arrays(6, 2, odd=False)
    a["scales"][1, 2] = bad
    a["scales"][4, 2] = bad
    a["sh_rest"][0, 7, 1] = bad  # coefficient 7 (0-based) of G -> f_rest_{8 + 7}
    p = tmp_path / "nan.ply"
    write_ply(p, **a, check_finite=False)
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, f"2 {word} in 'scale_2'", f"1 {word} in 'f_rest_15'")
    b = read_ply(p, allow_nonfinite=True)
    assert np.isnan(b["scales"][1, 2]) if word == "NaN" else np.isinf(b["scales"][1, 2])


def test_colours_beyond_float32_range_refused(tmp_path):
    """f_dc = 1e30 rendered Inf pixels (sRGB decoding overflowed float32, with a NumPy RuntimeWarning); such a model
    is refused, naming the property; the largest allowed magnitude still renders finite."""
    a = random_arrays(6, 3, odd=False)
    a["sh_dc"][2, 0] = 1e30
    p = tmp_path / "bright.ply"
    write_ply(p, **a)
    assert read_ply(p)["sh_dc"][2, 0] == np.float32(1e30)    # the file layer reads every finite float32
    with pytest.raises(ValueError) as ei:
        Gaussians.load_ply(p)
    one_line_error(ei, p, "1 colour coefficient beyond +-1e+12 (largest 1e+30 in 'f_dc_0')")
    a["sh_dc"][2, 0] = 0.0
    a["sh_rest"][1, 14, 2] = -5e12       # coefficient 14 of B -> f_rest_{30 + 14}
    write_ply(p, **a)
    with pytest.raises(ValueError) as ei:
        read_ply(p, renderable=True)
    one_line_error(ei, p, "(largest 5e+12 in 'f_rest_44')")


def test_largest_allowed_colour_renders_finite(tmp_path):
    """Every colour coefficient of the shipped model at +-MAX_ABS_SH_COEFFICIENT: the linear EXR render is finite."""
    import OpenEXR

    from test_cli import run

    root = Path(__file__).resolve().parents[1] / "scenes"
    a = read_ply(root / "tiny_gaussians.ply")
    rng = np.random.default_rng(0)
    for k in ("sh_dc", "sh_rest"):
        a[k] = np.float32(cv.MAX_ABS_SH_COEFFICIENT) * np.where(rng.random(a[k].shape) < 0.7, 1.0, -1.0)
    write_ply(tmp_path / "bright.ply", **a)
    r = run("render", tmp_path / "bright.ply", "--camera", root / "tiny_gaussians_camera.json", "-o",
            tmp_path / "bright.exr")
    assert r.returncode == 0, r.stderr
    assert "RuntimeWarning" not in r.stderr
    with OpenEXR.File(str(tmp_path / "bright.exr")) as f:
        img = np.asarray(next(iter(f.parts[0].channels.values())).pixels)
    assert np.all(np.isfinite(img)) and img.max() > 1e25


def test_double_overflow_reported_as_inf(tmp_path):
    a = random_arrays(2, 0, odd=False)
    names = ply_property_names(0)
    rows = table_of(a, names).astype(np.float64)
    rows[0, names.index("x")] = 1e300
    p = tmp_path / "ovf.ply"
    p.write_bytes(raw_ply(names, rows, types=["double"] * len(names)))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "1 Inf in 'x'")


@pytest.mark.parametrize("content,words", [
    (b"", ["empty"]),
    (b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4, ["not a PLY"]),
    (b"solid cube\nfacet normal 0 0 1\n", ["not a PLY"]),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n" + b"\0" * 64, ["end_header"]),
    (b"ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n", ["unsupported PLY format"]),
    (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty quad x\nend_header\n", ["unsupported PLY type", "'quad'"]),
    (b"ply\nformat ascii 1.0\nelement vertex 0\nfoo bar\nend_header\n", ["unknown keyword", "'foo'"]),
    (b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n", ["invalid element count"]),
    (b"ply\nelement vertex 0\nproperty float x\nend_header\n", ["no 'format'"]),
    (b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n",
     ["no 'vertex' element", "'face'"]),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\xff\nend_header\n", ["not ASCII"]),
])
def test_garbage_and_bad_headers(tmp_path, content, words):
    p = tmp_path / "garbage.ply"
    p.write_bytes(content)
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, *words)


def test_inconsistent_f_rest(tmp_path):
    a = random_arrays(2, 1, odd=False)
    names = ply_property_names(1)
    rows = table_of(a, names)
    p = tmp_path / "rest10.ply"
    p.write_bytes(raw_ply(names + ["f_rest_9"], np.concatenate([rows, rows[:, :1]], axis=1)))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "10 f_rest properties", "0, 9, 24 or 45")
    gap = [n if n != "f_rest_4" else "f_rest_11" for n in names]
    p = tmp_path / "gap.ply"
    p.write_bytes(raw_ply(gap, rows))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "f_rest_0..f_rest_8", "'f_rest_11'")


def test_integer_typed_attribute_and_duplicates(tmp_path):
    a = random_arrays(2, 0, odd=False)
    names = ply_property_names(0)
    types = ["float"] * len(names)
    types[names.index("opacity")] = "uchar"
    p = tmp_path / "int.ply"
    p.write_bytes(raw_ply(names, np.abs(np.round(table_of(a, names))), types=types))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "'opacity'", "integer type 'uchar'")
    p = tmp_path / "dup.ply"
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 2\n"
              + "".join(f"property float {n}\n" for n in names + ["x"]) + "end_header\n")
    p.write_bytes(header.encode() + bytes(2 * 4 * (len(names) + 1)))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "duplicate", "'x'")


def test_compressed_ply_and_missing_file(tmp_path):
    p = tmp_path / "compressed.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement chunk 1\nproperty float min_x\n"
                  b"element vertex 1\nproperty uint packed_position\nproperty uint packed_rotation\n"
                  b"property uint packed_scale\nproperty uint packed_color\nend_header\n" + b"\0" * 20)
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "compressed PLY")
    with pytest.raises(ValueError) as ei:
        read_ply(tmp_path / "nope.ply")
    one_line_error(ei, tmp_path / "nope.ply", "cannot read")


def test_ascii_truncated_and_bad_value(tmp_path):
    a = random_arrays(3, 0, odd=False)
    names = ply_property_names(0)
    p = tmp_path / "a.ply"
    good = raw_ply(names, table_of(a, names), fmt="ascii")
    p.write_bytes(good[:-30])
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p, "truncated")
    p.write_bytes(good.replace(b"end_header\n", b"end_header\nbogus ", 1))
    with pytest.raises(ValueError) as ei:
        read_ply(p)
    one_line_error(ei, p)


# ---------------------------------------------------------------------------------------------------- Mitsuba ellipsoids
def ellipsoid_params(shape) -> dict[str, np.ndarray]:
    p = mi.traverse(shape)
    return {"data": np.array(p["data"]).reshape(-1, 10), "opacities": np.array(p["opacities"]),
            "sh_coeffs": np.array(p["sh_coeffs"]), "extent": p["extent"], "keys": sorted(p.keys())}


def test_libllvm_selected():
    # Mitsuba's own code (and dr.minimum/maximum) needs libLLVM >= 16; the venv's .pth selects libLLVM 23.
    path = os.environ.get("DRJIT_LIBLLVM_PATH", "")
    assert path and os.path.exists(path), "DRJIT_LIBLLVM_PATH is not set to an existing libLLVM"


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ellipsoids_shape_loads_our_ply(tmp_path, degree):
    a = random_arrays(23, degree, seed=40 + degree, odd=False)
    a["scales"][0] = [-20.0, 0.0, 2.0]       # exp(-20) < 1e-6: floored by the loader
    a["opacities"][:2] = [-30.0, 30.0]       # clipped to [1e-8, 1]
    a["rotations"][1] = [-3.0, 0.0, 0.0, 0.0]  # no sign canonicalization
    path = tmp_path / "ell.ply"
    write_ply(path, **a)
    shape = mi.load_dict({"type": "ellipsoids", "filename": str(path)})
    got = ellipsoid_params(shape)
    assert got["keys"] == ["data", "extent", "extent_adaptive_clamping", "opacities", "sh_coeffs"]
    assert got["extent"] == 3.0
    n = a["means"].shape[0]

    # centres: exact copies
    assert np.array_equal(got["data"][:, 0:3], a["means"])
    # sigma = max(exp(scale), 1e-6), no other factor
    sigma = np.maximum(np.exp(a["scales"].astype(np.float64)), 1e-6)
    np.testing.assert_allclose(got["data"][:, 3:6], sigma, rtol=3e-7)
    assert np.all(got["data"][0, 3] == np.float32(1e-6))
    # quaternion: (x, y, z, w), normalized
    q = a["rotations"].astype(np.float64)
    q = q[:, [1, 2, 3, 0]] / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(got["data"][:, 6:10], q, atol=2e-7)
    assert np.array_equal(got["data"][1, 6:10], [0.0, 0.0, 0.0, -1.0])
    # opacities: sigmoid, clipped
    alpha = np.clip(1.0 / (1.0 + np.exp(-a["opacities"].astype(np.float64))), 1e-8, 1.0)
    np.testing.assert_allclose(got["opacities"], alpha, rtol=3e-7)
    # SH: coefficient-major, RGB-interleaved, DC first -- exact copies
    expect_sh = np.concatenate([a["sh_dc"][:, None, :], a["sh_rest"]], axis=1).reshape(-1)
    assert np.array_equal(got["sh_coeffs"], expect_sh)
    assert got["sh_coeffs"].size == n * 3 * (degree + 1) ** 2

    # our NumPy model of the loader agrees (to an ulp of exp), and inverts back to the raw values
    lay = cv.to_ellipsoids_layout(**a)
    np.testing.assert_allclose(got["data"], lay["data"], rtol=2.5e-7, atol=1e-12)
    np.testing.assert_allclose(got["opacities"], lay["opacities"], rtol=2.5e-7)
    assert np.array_equal(got["sh_coeffs"], lay["sh_coeffs"].reshape(-1))
    back = cv.from_ellipsoids_layout(got["data"], got["opacities"], got["sh_coeffs"])
    keep = slice(2, None)  # rows 0, 1 were floored / clipped on purpose
    assert np.array_equal(back["means"], a["means"])
    np.testing.assert_allclose(back["scales"][1:], a["scales"][1:], atol=1e-6)
    # logit of a float32 alpha near 1 is ill-conditioned: compare in alpha space
    np.testing.assert_allclose(cv.sigmoid(back["opacities"][keep]), cv.sigmoid(a["opacities"][keep]), atol=1.2e-7)
    assert np.array_equal(back["sh_dc"], a["sh_dc"]) and np.array_equal(back["sh_rest"], a["sh_rest"])
    np.testing.assert_allclose(cv.normalize_quat(back["rotations"]), cv.normalize_quat(a["rotations"]), atol=2e-7)


def test_ellipsoids_scale_factor_is_a_plain_multiplier(tmp_path):
    a = random_arrays(4, 0, seed=1, odd=False)
    path = tmp_path / "s.ply"
    write_ply(path, **a)
    base = ellipsoid_params(mi.load_dict({"type": "ellipsoids", "filename": str(path)}))
    scaled = ellipsoid_params(mi.load_dict({"type": "ellipsoids", "filename": str(path), "scale_factor": 2.0}))
    np.testing.assert_allclose(scaled["data"][:, 3:6], 2.0 * base["data"][:, 3:6], rtol=1e-7)
    assert np.array_equal(scaled["data"][:, [0, 1, 2, 6, 7, 8, 9]], base["data"][:, [0, 1, 2, 6, 7, 8, 9]])


def test_ellipsoids_shape_dict_matches_file_load(tmp_path):
    a = random_arrays(12, 2, seed=2, odd=False)
    path = tmp_path / "d.ply"
    write_ply(path, **a)
    from_file = ellipsoid_params(mi.load_dict({"type": "ellipsoids", "filename": str(path)}))
    from_dict = ellipsoid_params(mi.load_dict(cv.ellipsoids_shape_dict(**a)))
    assert from_dict["keys"] == from_file["keys"]
    np.testing.assert_allclose(from_dict["data"], from_file["data"], rtol=2.5e-7, atol=1e-12)
    np.testing.assert_allclose(from_dict["opacities"], from_file["opacities"], rtol=2.5e-7)
    assert np.array_equal(from_dict["sh_coeffs"], from_file["sh_coeffs"])


def test_convert_ply_makes_foreign_files_loadable_by_ellipsoids(tmp_path):
    rng = np.random.default_rng(0)
    a = random_arrays(7, 1, seed=9, odd=False)
    names, types, rows = supersplat_like(a, rng)
    src = tmp_path / "foreign.ply"
    src.write_bytes(raw_ply(names, rows, types=types))
    with pytest.raises(Exception, match="Invalid structure"):
        mi.load_dict({"type": "ellipsoids", "filename": str(src)})  # no normals, shuffled: Mitsuba refuses it
    dst = tmp_path / "converted.ply"
    convert_ply(src, dst)
    got = ellipsoid_params(mi.load_dict({"type": "ellipsoids", "filename": str(dst)}))
    assert np.array_equal(got["data"][:, 0:3], a["means"])
    expect_sh = np.concatenate([a["sh_dc"][:, None, :], a["sh_rest"]], axis=1).reshape(-1)
    assert np.array_equal(got["sh_coeffs"], expect_sh)
