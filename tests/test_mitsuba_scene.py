"""Mitsuba scene files as datasets: errors, camera rigs, declared sensors, cached references, initial points, the
sRGB-encoded training targets, the Gaussian scene written after a run, and ``mi-gs optimize scene.xml`` end to end."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

import mi_gaussians as mig
from mi_gaussians.config import SceneConfig, TriangulateConfig
from mi_gaussians.data import scene_init, scene_references
from mi_gaussians.data.scene_dataset import load_scene_dataset
from mi_gaussians.data.scene_file import load_scene, referenced_files, scene_bbox
from mi_gaussians.data.scene_references import cache_key
from mi_gaussians.data.scene_rig import look_at_camera, scene_views
from mi_gaussians.data.images import read_image
from mi_gaussians.imwrite import linear_to_srgb, srgb_to_linear
from mi_gaussians.plugins.scene_xml import write_gaussian_scene

from test_cli import assert_one_line_error, run

ROOT = Path(__file__).resolve().parents[1]

SENSOR = """
    <sensor type="perspective" id="{id}">
        <float name="fov" value="{fov}"/>
        <transform name="to_world"><lookat origin="{origin}" target="0, 0.3, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="{w}"/><integer name="height" value="{h}"/>
            <string name="pixel_format" value="rgba"/><rfilter type="box"/>
        </film>
    </sensor>"""

BODY = """
    <integrator type="path"><integer name="max_depth" value="3"/><boolean name="hide_emitters" value="true"/></integrator>
    <emitter type="constant"><rgb name="radiance" value="{sky}"/></emitter>
    <emitter type="directional"><vector name="direction" value="-0.3, -1, -0.2"/><rgb name="irradiance" value="2"/></emitter>
    <shape type="sphere" id="ball">
        <point name="center" value="0, 0.35, 0"/><float name="radius" value="0.35"/>
        <bsdf type="diffuse">
            <texture type="checkerboard" name="reflectance">
                <rgb name="color0" value="0.8, 0.2, 0.1"/><rgb name="color1" value="0.1, 0.4, 0.8"/>
                <transform name="to_uv"><scale x="4" y="2"/></transform>
            </texture>
        </bsdf>
    </shape>
    <shape type="rectangle" id="ground">
        <transform name="to_world"><rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>
    </shape>"""


def write_scene(path: Path, sensors: list[str] | None = None, sky: str = "0.5, 0.55, 0.6", w: int = 32, h: int = 32,
                spp: int = 8, fov: float = 45.0) -> Path:
    if sensors is None:
        sensors = [SENSOR.format(id="cam", fov=fov, origin="2.2, 1.6, 2.2", spp=spp, w=w, h=h)]
    path.write_text('<scene version="3.0.0">' + "".join(sensors) + BODY.format(sky=sky) + "\n</scene>\n")
    return path


@pytest.fixture
def scene_file(tmp_path) -> Path:
    return write_scene(tmp_path / "scene.xml")


# ------------------------------------------------------------------------------------------------ bad scene files
BAD_SCENES = {
    "syntax": ('<scene version="3.0.0">\n<shape type="sphere">\n</scene>\n', "mismatch"),
    "missing_mesh": ('<scene version="3.0.0"><shape type="ply"><string name="filename" value="gone.ply"/></shape>'
                     "</scene>", "gone.ply"),
    "missing_texture": ('<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" '
                        'name="reflectance"><string name="filename" value="gone.png"/></texture></bsdf></shape>'
                        "</scene>", "gone.png"),
    "no_shapes": ('<scene version="3.0.0"><emitter type="constant"/></scene>', "no shapes"),
}


@pytest.mark.parametrize("kind", sorted(BAD_SCENES))
def test_bad_scene_files_give_one_line_errors(tmp_path, kind):
    text, needle = BAD_SCENES[kind]
    p = tmp_path / f"{kind}.xml"
    p.write_text(text)
    with pytest.raises(ValueError) as e:
        load_scene(p)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(p)) and needle in msg, msg
    assert not msg.split(": ", 1)[1].startswith("["), msg      # Mitsuba's "[parser.cpp:...]" prefix removed


def test_cli_bad_scene_files(tmp_path):
    for kind in ("syntax", "no_shapes"):
        p = tmp_path / f"{kind}.xml"
        p.write_text(BAD_SCENES[kind][0])
        assert_one_line_error(run("optimize", p, "-o", tmp_path / f"out_{kind}"), str(p), BAD_SCENES[kind][1])
    assert_one_line_error(run("optimize", tmp_path / "nope.xml", "-o", tmp_path / "o"), "nope.xml", "not found")
    assert not (tmp_path / "out_syntax" / "point_cloud.ply").exists()


def test_referenced_files_resolve_like_mitsuba(tmp_path):
    """Names resolve against the top scene's folder first (also inside included files), with $parameters."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "tex.png").write_bytes(b"x")
    (tmp_path / "mesh.ply").write_bytes(b"y")                 # next to main.xml, named from sub/part.xml
    (tmp_path / "sub" / "local.ply").write_bytes(b"z")       # next to the including file only
    (tmp_path / "other.ply").write_bytes(b"w")
    (tmp_path / "sub" / "part.xml").write_text(
        '<scene version="3.0.0"><shape type="ply"><string name="filename" value="mesh.ply"/></shape>'
        '<shape type="ply"><string name="filename" value="local.ply"/></shape></scene>')
    main = tmp_path / "main.xml"
    main.write_text('<scene version="3.0.0"><default name="m" value="tex.png"/><include filename="sub/part.xml"/>'
                    '<texture type="bitmap" id="t"><string name="filename" value="$m"/></texture>'
                    '<string name="filename" value="$unknown"/></scene>')
    assert sorted(p.name for p in referenced_files(main)) == ["local.ply", "mesh.ply", "part.xml", "tex.png"]
    assert "other.ply" in [p.name for p in referenced_files(main, ["m=other.ply"])]


def test_cache_key_follows_referenced_file_contents(scene_file, tmp_path):
    tex = tmp_path / "t.png"
    from PIL import Image

    Image.new("RGB", (4, 4), (200, 10, 10)).save(tex)
    text = scene_file.read_text().replace(
        '<rgb name="reflectance" value="0.5"/>',
        '<texture type="bitmap" name="reflectance"><string name="filename" value="t.png"/></texture>')
    scene_file.write_text(text)
    scene = load_scene(scene_file)
    v = scene_views(scene, scene_file, SceneConfig(views=2, test_views=1))
    k1 = cache_key(scene_file, v)
    Image.new("RGB", (4, 4), (10, 200, 10)).save(tex)
    assert cache_key(scene_file, v) != k1


# ------------------------------------------------------------------------------------------------ camera rigs
def _elevation(cams, center, up):
    d = np.stack([c.center - center for c in cams])
    return np.degrees(np.arcsin(d @ up / np.linalg.norm(d, axis=1)))


def test_hemisphere_rig_geometry(scene_file):
    import mitsuba as mi

    scene = load_scene(scene_file)
    cfg = SceneConfig(views=40, test_views=6, radius=3.0)
    v = scene_views(scene, scene_file, cfg, seed=3)
    assert (len(v.train), len(v.test), v.source, v.spp) == (40, 6, "hemisphere", 8)
    lo, hi = scene_bbox(scene)
    center = 0.5 * (lo + hi)
    up = np.array([0.0, 1.0, 0.0])       # the sensor's up
    for c in v.train + v.test:
        assert abs(np.linalg.norm(c.center - center) - 3.0) < 1e-9
        uv, z = c.project(center[None])
        assert z[0] > 0 and np.allclose(uv[0], [c.cx, c.cy], atol=1e-6)   # looks at the centre
        assert (c.width, c.height) == (32, 32) and abs(math.degrees(c.fov_x) - 45.0) < 1e-9
    el = _elevation(v.train + v.test, center, up)
    assert el.min() >= 10.0 - 1e-6 and el.max() <= 75.0 + 1e-6
    # evenly spread: elevations fill the band, azimuths cover the circle
    assert el.max() - el.min() > 50.0
    # seeded: same seed same cameras, other seed other cameras; test poses differ from training poses
    again = scene_views(scene, scene_file, cfg, seed=3)
    other = scene_views(scene, scene_file, cfg, seed=4)
    assert all(np.array_equal(a.world_to_camera, b.world_to_camera) for a, b in zip(v.train, again.train))
    assert not np.allclose(v.train[0].world_to_camera, other.train[0].world_to_camera)
    dmin = min(np.linalg.norm(t.center - c.center) for t in v.test for c in v.train)
    assert dmin > 1e-3
    del mi


def test_sphere_rig_and_overrides(scene_file):
    scene = load_scene(scene_file)
    cfg = SceneConfig(rig="sphere", views=30, test_views=0, resolution=(48,), fov=60.0, up=(0.0, 0.0, 1.0),
                      spp=4)
    v = scene_views(scene, scene_file, cfg)
    lo, hi = scene_bbox(scene)
    center = 0.5 * (lo + hi)
    el = _elevation(v.train, center, np.array([0.0, 0.0, 1.0]))
    assert el.min() < -45 and el.max() > 45 and v.test == [] and v.spp == 4
    c = v.train[0]
    assert (c.width, c.height) == (48, 48) and abs(math.degrees(c.fov_x) - 60.0) < 1e-9
    # default radius: the bounding sphere fits in the field of view
    r = np.linalg.norm(c.center - center)
    assert abs(r - 0.5 * np.linalg.norm(hi - lo) / math.sin(math.radians(30.0))) < 1e-6


def test_rig_takes_the_sensors_aspect_and_rejects_bad_options(tmp_path):
    p = write_scene(tmp_path / "wide.xml", w=40, h=20)
    scene = load_scene(p)
    v = scene_views(scene, p, SceneConfig(views=2, test_views=1, resolution=(80,)))
    assert (v.train[0].width, v.train[0].height) == (80, 40)
    for bad in (dict(rig="ring"), dict(views=0), dict(fov=190.0), dict(radius=-1.0), dict(up=(0.0, 0.0, 0.0)),
                dict(rig="sensors")):
        with pytest.raises(ValueError):
            scene_views(scene, p, dataclasses.replace(SceneConfig(), **bad))


ORTHO = """
    <sensor type="orthographic" id="top">
        <transform name="to_world"><lookat origin="0, 3, 0" target="0, 0, 0" up="0, 0, 1"/></transform>
        <sampler type="independent"><integer name="sample_count" value="6"/></sampler>
        <film type="hdrfilm"><integer name="width" value="36"/><integer name="height" value="24"/></film>
    </sensor>"""


def test_single_orthographic_sensor_is_not_replaced_silently(tmp_path):
    """A scene whose only sensor is orthographic was trained on a 40-degree perspective rig without a word; it is now
    refused unless a field of view is given, and then the rig keeps the sensor's film, up direction and samples."""
    p = write_scene(tmp_path / "ortho.xml", sensors=[ORTHO])
    scene = load_scene(p)
    with pytest.raises(ValueError) as e:
        scene_views(scene, p, SceneConfig(views=2, test_views=1))
    assert str(e.value) == (f"{p}: the scene's sensor 'top' (OrthographicCamera) is not perspective, and the generated "
                            "camera rig is; give --fov DEGREES to train on a perspective rig anyway (the rasterizer "
                            "renders pinhole cameras only)")
    v = scene_views(scene, p, SceneConfig(views=3, test_views=1, fov=30.0))
    assert (v.train[0].width, v.train[0].height, v.spp) == (36, 24, 6)
    assert math.isclose(math.degrees(v.train[0].fov_x), 30.0, rel_tol=1e-9)
    for c in v.train:     # up is +z: every camera's image "up" (-y in OpenCV axes) leans towards +z
        assert -c.camera_to_world[2, 1] > 0


def test_single_orthographic_sensor_cli(tmp_path):
    p = write_scene(tmp_path / "ortho.xml", sensors=[ORTHO])
    r = run("optimize", p, "-o", tmp_path / "out", "--iterations", "1", "--views", "2", "--test-views", "1")
    assert_one_line_error(r, f"{p}: the scene's sensor 'top' (OrthographicCamera) is not perspective")
    assert not (tmp_path / "out").exists()


def test_declared_sensors_are_the_views(tmp_path):
    import mitsuba as mi

    origins = [f"{2.5 * math.cos(a):.4f}, 1.2, {2.5 * math.sin(a):.4f}" for a in np.linspace(0, 6, 10)]
    sensors = [SENSOR.format(id=f"s{i}", fov=40, origin=o, spp=4, w=24, h=16) for i, o in enumerate(origins)]
    p = write_scene(tmp_path / "multi.xml", sensors=sensors)
    scene = load_scene(p)
    v = scene_views(scene, p, SceneConfig())
    assert v.source == "sensors" and len(v.train) == 8 and len(v.test) == 2
    assert [c.name for c in v.test] == ["sensor_000", "sensor_008"]
    want = mig.Camera.from_mitsuba(scene.sensors()[3])
    assert np.allclose(v.train[2].world_to_camera, want.world_to_camera) and v.train[2].fx == want.fx
    del mi


def test_rig_cameras_agree_with_mitsuba_pixels(bright_sphere):
    """A rig camera's projection of a point is where Mitsuba renders it, through Camera.to_mitsuba."""
    cam = look_at_camera([2.0, 1.5, -1.0], [0.0, 0.2, 0.0], [0.0, 1.0, 0.0], 64, 48, 50.0, "c")
    p = np.array([0.25, 0.35, 0.1])
    img = bright_sphere.render(cam, p, 0.03)
    uv, _ = cam.project(p[None])
    assert np.linalg.norm(bright_sphere.centroid(img) - uv[0]) < 0.5


# ------------------------------------------------------------------------------------------------ references
def test_references_are_cached_and_keyed(tmp_path, monkeypatch):
    p = write_scene(tmp_path / "scene.xml", w=16, h=16, spp=4)
    cfg = SceneConfig(views=3, test_views=1, init="random", init_points=100)
    ds = load_scene_dataset(p, cfg, cache_root=tmp_path / "refs", progress=False)
    files = sorted((tmp_path / "refs").glob("*/*/*.exr"))
    assert len(files) == 4 and ds.references.parent == tmp_path / "refs"
    img = read_image(files[0])
    assert img.shape == (16, 16, 4) and np.all(np.isfinite(img))
    rig = json.loads((ds.references / "rig.json").read_text())
    assert len(rig["train"]) == 3 and rig["spp"] == 4

    calls = []
    real = scene_references.render_reference
    monkeypatch.setattr(scene_references, "render_reference", lambda *a, **k: calls.append(1) or real(*a, **k))
    load_scene_dataset(p, cfg, cache_root=tmp_path / "refs", progress=False)
    assert calls == []                                  # a re-run renders nothing
    files[0].unlink()
    load_scene_dataset(p, cfg, cache_root=tmp_path / "refs", progress=False)
    assert len(calls) == 1                              # only what is missing
    # the viewer's load renders nothing: the view whose reference is gone has no picture
    from mi_gaussians.viewer_entries import dataset_entries

    files[0].unlink()
    ds = load_scene_dataset(p, cfg, cache_root=tmp_path / "refs", progress=False, render_missing=False)
    assert len(calls) == 1 and not files[0].exists()
    assert [v.image_path for v in ds.train + ds.test if not v.image_path.is_file()] == [files[0]]
    entries = dataset_entries(ds)
    assert [e.reference is None for e in entries].count(True) == 1 and len(entries) == 4
    load_scene_dataset(p, cfg, cache_root=tmp_path / "refs", progress=False)
    assert len(calls) == 2 and files[0].is_file()
    load_scene_dataset(p, dataclasses.replace(cfg, spp=2), cache_root=tmp_path / "refs", progress=False)
    assert len(calls) == 6                              # another sample count: another key
    write_scene(p, w=16, h=16, spp=4, sky="0.2, 0.2, 0.2")
    load_scene_dataset(p, cfg, cache_root=tmp_path / "refs", progress=False)
    assert len(calls) == 10 and len(list((tmp_path / "refs").iterdir())) == 3   # an edited scene: another key


def test_background_is_in_the_training_colour_space(tmp_path):
    """Empty pixels of the targets show the background itself, encoded or linear, as the Gaussians are drawn over."""
    p = write_scene(tmp_path / "scene.xml", w=16, h=16, spp=4)
    for linear in (False, True):
        cfg = SceneConfig(views=2, test_views=1, init="random", init_points=10, radius=6.0, linear=linear)
        ds = load_scene_dataset(p, cfg, cache_root=tmp_path / "refs", background=(0.5, 0.25, 0.0),
                                progress=False)
        v = ds.train[0]
        empty = v.load_alpha() == 0
        assert empty.sum() > 10
        assert np.allclose(v.load_image()[empty], [0.5, 0.25, 0.0], atol=1e-5), linear


def test_training_targets_are_srgb_encoded_hdr(tmp_path):
    p = write_scene(tmp_path / "scene.xml", w=16, h=16, spp=4, sky="3, 3, 3")     # bright: values above 1
    base = SceneConfig(views=2, test_views=1, init="random", init_points=10)
    enc = load_scene_dataset(p, base, cache_root=tmp_path / "refs", progress=False)
    lin = load_scene_dataset(p, dataclasses.replace(base, linear=True), cache_root=tmp_path / "refs",
                                progress=False)
    assert (enc.color_space, lin.color_space) == ("srgb", "linear")
    raw = read_image(enc.references / "train" / "train_000.exr")[..., :3]
    a, b = enc.train[0].load_image(), lin.train[0].load_image()
    assert np.allclose(b, raw) and np.allclose(a, linear_to_srgb(np.maximum(raw, 0)), atol=1e-6)
    assert raw.max() > 1.0 and a.max() > 1.0          # HDR kept, not clipped
    assert np.allclose(srgb_to_linear(a), b, rtol=1e-4, atol=1e-6)


# ------------------------------------------------------------------------------------------------ initial points
def test_shape_samples_lie_on_the_shapes(scene_file):
    scene = load_scene(scene_file)
    xyz = scene_init.sample_surface_points(scene, 4000, seed=1)
    on_ball = np.abs(np.linalg.norm(xyz - [0, 0.35, 0], axis=1) - 0.35) < 1e-4
    on_ground = (np.abs(xyz[:, 1]) < 1e-5) & (np.abs(xyz[:, [0, 2]]) <= 1 + 1e-5).all(axis=1)
    assert np.all(on_ball | on_ground)
    # uniform by area: sphere 4 pi r^2 = 1.539 vs rectangle 4
    frac = on_ball.mean()
    want = 4 * math.pi * 0.35 ** 2 / (4 * math.pi * 0.35 ** 2 + 4.0)
    assert abs(frac - want) < 4 * math.sqrt(want * (1 - want) / 4000)


def test_visibility_and_colours_from_views(scene_file):
    scene = load_scene(scene_file)
    cam = look_at_camera([0.0, 0.35, 3.0], [0.0, 0.35, 0.0], [0, 1, 0], 32, 32, 40.0, "c")
    front, back = np.array([[0.0, 0.35, 0.35]]), np.array([[0.0, 0.35, -0.35]])
    assert scene_init.visible_from(scene, cam, front)[0][0]
    assert not scene_init.visible_from(scene, cam, back)[0][0]            # behind the ball
    outside = np.array([[5.0, 0.35, 0.0]])
    assert not scene_init.visible_from(scene, cam, outside)[0][0]         # out of the image
    img = np.zeros((32, 32, 3), np.float32)
    img[..., 0] = np.arange(32)[None, :]
    rgb, seen = scene_init.colour_from_views(scene, np.concatenate([front, back]), [cam, cam], [img, img + 1])
    assert seen.tolist() == [True, False]
    u = int(np.floor(cam.project(front)[0][0, 0]))
    assert np.allclose(rgb[0], [u + 0.5, 0.5, 0.5])                       # the mean over both views


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ R.T + [1.0, -2.0, 0.5]
    s, R2, t = scene_init.umeyama(src, dst)
    assert abs(s - 2.5) < 1e-9 and np.allclose(R2, R) and np.allclose(t, [1.0, -2.0, 0.5])


def test_the_alignment_of_sfm_cameras_holds_against_misregistered_ones():
    """64 cameras on a sphere of radius 4, 7 of them registered mirrored through the object (as structure from motion
    does with some views of a symmetric scene): a least-squares fit over every camera is dragged off; the consensus
    recovers the similarity and names the 57 cameras that agree. With most cameras wrong it finds no majority."""
    rng = np.random.default_rng(1)
    truth = rng.normal(size=(64, 3))
    truth = 4.0 * truth / np.linalg.norm(truth, axis=1, keepdims=True)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    s_true, t_true = 0.7, np.array([0.3, -1.0, 2.0])
    sfm = ((truth - t_true) @ R) / s_true                      # the inverse similarity: sfm -> truth is (s, R, t)
    sfm[:7] = -sfm[:7]                                          # mirrored registrations
    s, R2, t = scene_init.umeyama(sfm, truth)
    assert np.abs(s * sfm @ R2.T + t - truth).max() > 1.0       # (the plain fit: off by a quarter of the rig)
    s, R2, t, agree = scene_init.robust_umeyama(sfm, truth)
    assert abs(s - s_true) < 1e-9 and np.allclose(R2, R) and np.allclose(t, t_true)
    assert agree.tolist() == [False] * 7 + [True] * 57
    scrambled = sfm.copy()
    scrambled[:40] = rng.permutation(scrambled[:40])
    _, _, _, agree = scene_init.robust_umeyama(scrambled, truth)
    assert agree.sum() < 32


def test_dataset_from_shapes_init(scene_file, tmp_path):
    cfg = SceneConfig(views=6, test_views=1, init_points=3000, resolution=(24,))
    ds = load_scene_dataset(scene_file, cfg, cache_root=tmp_path / "refs", progress=False)
    assert ds.layout == "mitsuba" and 0 < len(ds.points_xyz) <= 3000
    assert ds.points_rgb.shape == ds.points_xyz.shape and np.all(ds.points_rgb >= 0)
    assert ds.extent > 0 and len(ds.train) == 6 and len(ds.test) == 1


# ------------------------------------------------------------------------------------------------ Gaussian scenes
def test_written_gaussian_scene_renders_the_model(tmp_path):
    import mitsuba as mi

    g = mig.Gaussians.load_ply(ROOT / "scenes" / "tiny_gaussians.ply")
    cam = mig.Camera.from_json(ROOT / "scenes" / "tiny_gaussians_camera.json").scaled(96, 72)
    (tmp_path / "m.ply").write_bytes((ROOT / "scenes" / "tiny_gaussians.ply").read_bytes())
    want = np.array(mig.render(g, cam, background=(0.2, 0.2, 0.2)).rgb)
    for cs in ("linear", "srgb"):
        write_gaussian_scene(tmp_path / f"g_{cs}.xml", "m.ply", cam, cs, background=(0.2, 0.2, 0.2))
        img = np.array(mi.render(mi.load_file(str(tmp_path / f"g_{cs}.xml"))))
        assert img.shape == (72, 96, 4)
        expect = want if cs == "linear" else srgb_to_linear(want)
        assert np.abs(img[..., :3] - expect).max() < 1e-4, cs


# ------------------------------------------------------------------------------------------------ end to end
def test_optimize_scene_xml_end_to_end(tmp_path):
    """``mi-gs optimize scene.xml``: references rendered and cached, PSNR rises, outputs written, then
    ``--overwrite`` reuses the references and ``mi-gs eval`` reproduces the metrics."""
    p = write_scene(tmp_path / "scene.xml", w=40, h=40, spp=64)
    out = tmp_path / "run"
    rig = ["optimize", p, "-o", out, "--views", 16, "--test-views", 3, "--init-points", 4000]   # (not --quiet: the
    # lines on the references are information, which --quiet leaves out)
    args = rig + ["--iterations", 300, "--eval-every", 50]
    res = run(*args)
    assert res.returncode == 0, res.stderr
    assert "rendering 19 of 19 references" in res.stderr
    for f in ("point_cloud.ply", "metrics.json", "config.json", "curves.png", "gaussians.xml",
              "renders/test_000.exr", "renders/test_000.png", "compare/test_000.png"):
        assert (out / f).is_file(), f
    assert len(list((out / "references").glob("*/test/*.exr"))) == 3
    m = json.loads((out / "metrics.json").read_text())
    last = m["mean"]["psnr"]
    # the initial model (the same cached references and initial points, in this process) scores much lower
    from mi_gaussians.config import TrainConfig
    from mi_gaussians.evaluate import evaluate_views, summarize

    cfg = TrainConfig.from_dict(json.loads((out / "config.json").read_text())["train"])
    ds = load_scene_dataset(p, cfg.scene, cache_root=out / "references", progress=False)
    g0 = mig.Gaussians.from_points(ds.points_xyz, ds.points_rgb, sh_degree=3)
    first = summarize(evaluate_views(g0, ds.test, (0, 0, 0), with_lpips=False)[0])["psnr"]
    assert last > 25.0 and last > first + 5.0, (first, last)     # measured: 20.6 -> 27.8 dB
    # the EXR render is linear: the PNG is its sRGB encoding
    exr = read_image(out / "renders" / "test_000.exr")[..., :3]
    png = read_image(out / "renders" / "test_000.png")[..., :3]
    assert np.abs(linear_to_srgb(np.clip(exr, 0, 1)) - png).max() < 1.5 / 255
    # the saved scene renders the model through Mitsuba
    assert run("render", out / "gaussians.xml", "-o", tmp_path / "g.exr").returncode == 0
    # eval recomputes the same metrics from the cached references
    res = run("eval", out)
    assert res.returncode == 0, res.stderr
    assert abs(json.loads(res.stdout)["psnr"] - last) < 1e-3
    assert "rendering" not in res.stderr
    # a second run into the same folder needs --overwrite, and renders nothing
    assert_one_line_error(run(*args), "--overwrite")
    res = run(*rig, "--iterations", 20, "--overwrite", "--linear")
    assert res.returncode == 0, res.stderr
    assert "reusing the 19 cached references" in res.stderr
    assert json.loads((out / "config.json").read_text())["train"]["scene"]["linear"] is True
    assert 'name="color_space" value="linear"' in (out / "gaussians.xml").read_text()


def _run_in(cwd, *args):
    import subprocess
    import sys

    exe = Path(sys.executable).parent / "mi-gs"
    return subprocess.run([str(exe)] + [str(a) for a in args], capture_output=True, text=True, timeout=600, cwd=cwd)


def test_runs_find_their_references(tmp_path):
    """Relative output and cache folders, eval from elsewhere, --resume without --cache, an edited scene refused,
    and --overwrite that fails on a bad option keeps the earlier run."""
    p = write_scene(tmp_path / "scene.xml", w=24, h=24, spp=4)
    common = ["--views", 6, "--test-views", 1, "--init-points", 500, "--quiet"]
    res = _run_in(tmp_path, "optimize", "scene.xml", "-o", "rel_run", "--iterations", 20, "--cache", "refs", *common)
    assert res.returncode == 0, res.stderr
    run_dir = tmp_path / "rel_run"
    assert (tmp_path / "refs").is_dir() and not (run_dir / "references").exists()
    res = run("eval", run_dir)                                     # another working folder
    assert res.returncode == 0 and "rendering" not in res.stderr, res.stderr
    res = run("optimize", p, "-o", run_dir, "--resume")
    assert res.returncode == 0 and "reusing the 7 cached references" in res.stderr, res.stderr
    # a bad option with --overwrite changes nothing
    assert_one_line_error(run("optimize", p, "-o", run_dir, "--overwrite", "-r", 2), "film size")
    assert (run_dir / "point_cloud.ply").is_file() and (run_dir / "checkpoints" / "ckpt.npz").is_file()
    # the scene changed: resume and eval are refused before anything is rendered
    write_scene(p, w=24, h=24, spp=4, sky="0.1, 0.1, 0.1")
    assert_one_line_error(run("eval", run_dir, "--overwrite"), "changed")
    assert_one_line_error(run("optimize", p, "-o", run_dir, "--resume"), "changed")
    assert len(list((tmp_path / "refs").iterdir())) == 1


def test_linear_models_are_scored_on_display_images():
    from mi_gaussians.evaluate import display

    x = np.array([[[0.0, 0.5, 2.0]]], np.float32)
    assert np.allclose(display(x, "srgb"), [[[0.0, 0.5, 1.0]]])
    assert np.allclose(display(x, "linear"), np.clip(linear_to_srgb(x), 0, 1))


def test_integrator_rejects_unknown_colour_space():
    import mitsuba as mi

    with pytest.raises(Exception, match="color_space"):
        mi.load_dict({"type": "gaussian_splatting", "color_space": "aces"})


def test_resume_compares_scene_parameters_as_a_mapping(tmp_path):
    """``-D`` given again on --resume: the same parameters in another order continue the run; another value is
    refused, naming the option."""
    p = tmp_path / "param.xml"
    write_scene(p, w=24, h=24, spp=4)
    text = p.read_text().replace('<scene version="3.0.0">', '<scene version="3.0.0"><default name="sky" '
                                 'value="0.5"/><default name="lamp" value="2"/>', 1)
    p.write_text(text.replace('value="0.5, 0.55, 0.6"', 'value="$sky"').replace('name="irradiance" value="2"',
                                                                             'name="irradiance" value="$lamp"'))
    common = ["--views", 4, "--test-views", 1, "--init-points", 300, "--quiet", "-o", tmp_path / "run"]
    res = run("optimize", p, "--iterations", 5, "-D", "sky=0.4", "-D", "lamp=3", *common)
    assert res.returncode == 0, res.stderr
    res = run("optimize", p, "--resume", "--iterations", 8, "-D", "lamp=3", "-D", "sky=0.4", *common)
    assert res.returncode == 0, res.stderr
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["iterations"] == 8
    assert_one_line_error(run("optimize", p, "--resume", "-D", "lamp=3", "-D", "sky=0.5", *common),
                          "--define gives scene.defines")


def test_triangulate_init_puts_points_on_the_shapes_with_the_scenes_cameras(scene_file, tmp_path):
    """``--init triangulate``: SIFT points of the references triangulated with the exact cameras lie on the shapes
    (independent truth: points sampled densely on them), are cached per settings, and too few is one line."""
    from scipy.spatial import cKDTree

    objects = Path(__file__).resolve().parents[1] / "scenes" / "objects.xml"
    cfg = SceneConfig(views=24, test_views=1, init="triangulate", resolution=(192,), spp=8)
    ds = load_scene_dataset(objects, cfg, cache_root=tmp_path / "refs", progress=False)
    assert ds.points_from == "triangulate" and len(ds.points_xyz) >= TriangulateConfig().min_points
    surface = scene_init.sample_surface_points(load_scene(objects), 400_000, seed=0)
    size = float(np.linalg.norm(surface.max(axis=0) - surface.min(axis=0)))
    dist = cKDTree(surface).query(ds.points_xyz)[0]
    assert np.median(dist) < 0.01 * size, np.percentile(dist, [50, 90]) / size
    assert np.mean(dist < 0.03 * size) > 0.8
    cached = list((tmp_path / "refs").glob("*/triangulated_*/*/points.npz"))
    assert len(cached) == 1
    # (a small untextured scene: too few points, refused in one line naming the scene and what to do)
    small = SceneConfig(views=6, test_views=1, init="triangulate", resolution=(48,), spp=4)
    with pytest.raises(ValueError, match=rf"{scene_file.name}: .*triangulate\.min_points .*--init shapes"):
        load_scene_dataset(scene_file, small, cache_root=tmp_path / "refs", progress=False)
