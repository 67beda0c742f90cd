"""Shared fixtures: the Mitsuba variant, the shared datasets folder."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session", autouse=True)
def variant():
    """Every test runs with the llvm_ad_rgb variant selected (the CPU variant every machine has)."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return "llvm_ad_rgb"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` next to the repository (the datasets of SOURCES.md); skips when it is absent."""
    p = (Path(__file__).parents[1] / ".." / "shared" / "data").resolve()
    if not p.is_dir():
        pytest.skip(f"shared datasets not available ({p} is missing)")
    return p


class _BrightSphere:
    """Render a small emissive sphere through ``Camera.to_mitsuba`` and locate it (tests of camera geometry)."""

    @staticmethod
    def render(cam, center, radius: float, spp: int = 64):
        """(H, W) radiance of an emissive sphere of ``radius`` at world point ``center`` seen by ``cam``."""
        import mitsuba as mi
        import numpy as np

        sensor = cam.to_mitsuba()
        sensor["sampler"] = {"type": "independent", "sample_count": spp}
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "direct"},
            "sensor": sensor,
            "ball": {"type": "sphere", "center": [float(c) for c in center], "radius": radius,
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
        })
        return np.array(mi.render(scene, seed=1))[..., 0]

    @staticmethod
    def centroid(img):
        """Intensity centroid in pixel coordinates (pixel centres at +0.5), (2,)."""
        import numpy as np

        ys, xs = np.mgrid[0:img.shape[0], 0:img.shape[1]]
        w = img.sum()
        if not w > 0:
            raise AssertionError("nothing rendered")
        return np.array([(img * (xs + 0.5)).sum() / w, (img * (ys + 0.5)).sum() / w])


@pytest.fixture
def bright_sphere() -> _BrightSphere:
    return _BrightSphere()
