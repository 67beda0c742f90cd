"""The Mitsuba plugin: registration, mi.render through the rasterizer, differentiability, the shipped XML scene,
and compatibility of the same PLY with Mitsuba's own ray-traced Gaussians (ellipsoids + volprim_rf_basic)."""

from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_gaussians as mig
import scene_factory as sf
from mi_gaussians.imwrite import linear_to_srgb
from mi_gaussians.model.ply import write_ply

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def _scene_dict(ply, cam: mig.Camera, integrator=None, pixel_format="rgb"):
    sensor = cam.to_mitsuba()
    sensor["film"]["pixel_format"] = pixel_format
    return {"type": "scene", "integrator": integrator or {"type": "gaussian_splatting"}, "sensor": sensor,
            "gs": {"type": "ellipsoids", "filename": str(ply)}}


@pytest.fixture()
def model(tmp_path):
    params, _ = sf.random_scene(seed=5, n=60, sh_degree=2)
    cam = mig.Camera(64, 48, 60.0, 60.0, 36.5, 21.0, sf.generic_camera(64, 48).world_to_camera)
    path = tmp_path / "model.ply"
    write_ply(path, **params)
    return path, params, cam


def test_registered_for_active_and_later_variants(variant):
    integ = mi.load_dict({"type": "gaussian_splatting"})
    assert "GaussianSplattingIntegrator" in str(integ) and "antialiased=False" in str(integ)
    assert "antialiased=True" in str(mi.load_dict({"type": "gaussian_splatting", "antialiased": True}))
    mi.set_variant(variant.replace("_rgb", "_mono"))
    try:
        assert "GaussianSplattingIntegrator" in str(mi.load_dict({"type": "gaussian_splatting"}))
    finally:
        mi.set_variant(variant)


def test_mi_render_equals_library_render(model):
    path, params, cam = model
    scene = mi.load_dict(_scene_dict(path, cam, {"type": "gaussian_splatting", "background": 0.25,
                                                  "depth_aov": True}, pixel_format="rgba"))
    img = np.array(mi.render(scene))
    assert img.shape == (48, 64, 5)
    out = mig.render(mig.Gaussians.load_ply(path), cam, background=(0.25, 0.25, 0.25))
    # the shape stores normalized quaternions and exp(scale): float32 rounding differs by a few ulps
    np.testing.assert_allclose(img[..., :3], np.array(out.rgb), atol=2e-5)
    np.testing.assert_allclose(img[..., 3], np.array(out.alpha), atol=2e-5)
    np.testing.assert_allclose(img[..., 4], np.array(out.depth), rtol=1e-4, atol=1e-4)


def test_antialiased_parameter(model, tmp_path):
    """``antialiased=true`` renders the library's anti-aliased image, and the scene file written for such a model
    (gaussians.xml) carries the parameter; a default model's file does not mention it."""
    from mi_gaussians.config import RasterConfig
    from mi_gaussians.plugins.scene_xml import gaussian_scene_xml

    path, params, cam = model
    params["scales"] = params["scales"] - 2.0        # small footprints: the compensation matters
    write_ply(path, **params)
    scene = mi.load_dict(_scene_dict(path, cam, {"type": "gaussian_splatting", "antialiased": True}))
    img = np.array(mi.render(scene))
    g = mig.Gaussians.load_ply(path)
    aa = np.array(mig.render(g, cam, cfg=RasterConfig(antialiased=True)).rgb)
    plain = np.array(mig.render(g, cam).rgb)
    np.testing.assert_allclose(img, aa, atol=2e-5)
    assert np.abs(aa - plain).max() > 0.05
    xml = gaussian_scene_xml(tmp_path / "g.xml", "model.ply", cam, antialiased=True)
    assert '<boolean name="antialiased" value="true"/>' in xml
    (tmp_path / "g.xml").write_text(xml.replace("model.ply", str(path)))
    np.testing.assert_allclose(np.array(mi.render(mi.load_file(str(tmp_path / "g.xml"))))[..., :3], aa, atol=2e-5)
    assert "antialiased" not in gaussian_scene_xml(tmp_path / "g.xml", "model.ply", cam)
    # the header's recipe for Mitsuba's own ray tracer: the integrator element replaced, the scene loads
    import re

    traced = re.sub(r'<integrator type="gaussian_splatting">.*?</integrator>', '<integrator type="volprim_rf_basic"/>',
                    xml, flags=re.S)
    assert "volprim_rf_basic" in xml and 'type="gaussian_splatting"' not in traced
    mi.load_string(traced.replace("model.ply", str(path)))


def test_mi_render_is_differentiable(model):
    path, _, cam = model
    scene = mi.load_dict(_scene_dict(path, cam))
    params = mi.traverse(scene)
    keys = ["gs.data", "gs.opacities", "gs.sh_coeffs"]
    rng = np.random.default_rng(0)
    w = mi.Float(rng.normal(size=48 * 64 * 3).astype(np.float32))

    def loss_of(p):
        return dr.sum(mi.render(scene, params=p).array * w)

    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    dr.backward(loss_of(params))
    grads = {k: np.array(dr.grad(params[k])) for k in keys}
    for k in keys:
        assert np.all(np.isfinite(grads[k])) and np.count_nonzero(grads[k]) > 0, k
    # central finite differences of single entries (the largest gradients of each block; for data, the centres)
    base = {k: np.array(params[k]) for k in keys}
    for k, eps in (("gs.sh_coeffs", 1e-2), ("gs.opacities", 1e-3), ("gs.data", 2e-4)):
        g = grads[k].copy()
        if k == "gs.data":
            g.reshape(-1, 10)[:, 3:] = 0
        for i in np.argsort(-np.abs(g))[:4]:
            vals = []
            for sgn in (1, -1):
                b = base[k].copy()
                b[i] += sgn * eps
                params[k] = mi.Float(b)
                params.update()
                vals.append(float(loss_of(params)[0]))
            fd = (vals[0] - vals[1]) / (2 * eps)
            assert abs(fd - g[i]) <= 1e-2 * abs(g[i]), (k, i, fd, g[i])
        params[k] = mi.Float(base[k])
        params.update()


def test_shipped_xml_scene_renders_like_the_camera_json():
    scene = mi.load_file(str(SCENES / "tiny_gaussians.xml"))
    img = np.array(mi.render(scene))
    g = mig.Gaussians.load_ply(SCENES / "tiny_gaussians.ply")
    cam = mig.Camera.from_json(SCENES / "tiny_gaussians_camera.json")
    np.testing.assert_allclose(img, np.array(mig.render(g, cam).rgb), atol=2e-6)
    assert img.mean() > 0.05


def test_same_ply_ray_traced_by_mitsuba_matches():
    """Mitsuba's own ellipsoids + volprim_rf_basic on our PLY: the same picture (it differs by design: no 0.3
    dilation, peak-density ray evaluation, linear output from sRGB primitives)."""
    ours = np.array(mi.render(mi.load_file(str(SCENES / "tiny_gaussians.xml"))))
    rt_scene = mi.load_file(str(SCENES / "tiny_gaussians.xml"), integrator="volprim_rf_basic", spp=4)
    rt = linear_to_srgb(np.array(mi.render(rt_scene)))
    psnr = -10 * np.log10(np.mean((rt - ours) ** 2))
    assert psnr > 20.0, psnr


def test_errors():
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "gaussian_splatting"},
                          "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
                          "s": {"type": "sphere"}})
    with pytest.raises(Exception) as info:
        mi.render(scene)
    chain, e = [], info.value
    while e is not None:      # mi.render wraps plugin errors in dr.custom's own exception
        chain.append(str(e))
        e = e.__cause__ or e.__context__
    assert any("no 'ellipsoids' shape" in m for m in chain), chain
    with pytest.raises(Exception, match="sh_degree"):
        mi.load_dict({"type": "gaussian_splatting", "sh_degree": 7})
