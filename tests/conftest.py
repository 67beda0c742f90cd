"""Shared fixtures: the Mitsuba variant, the shared datasets folder.

Every test runs with one Mitsuba variant, ``llvm_ad_rgb`` unless ``pytest --variant NAME`` names another (e.g.
``cuda_ad_rgb`` on a GPU machine: the whole suite then runs on CUDA unchanged). Tests that start ``mi-gs`` in a
subprocess get the CLI's own default (``cuda_ad_rgb`` where a CUDA device exists, else ``llvm_ad_rgb``)."""

from __future__ import annotations

from pathlib import Path

import pytest


DEFAULT_VARIANT = "llvm_ad_rgb"     # the CPU variant every machine has


def pytest_addoption(parser):
    parser.addoption("--variant", default=DEFAULT_VARIANT,
                     help=f"Mitsuba variant every test runs with (default {DEFAULT_VARIANT}; e.g. cuda_ad_rgb)")


def pytest_configure(config):
    """Select the variant before collection (test modules import mi_gaussians, which registers its plugins)."""
    import mitsuba as mi

    name = config.getoption("--variant")
    if name not in mi.variants():
        raise pytest.UsageError(f"--variant {name}: not a Mitsuba variant of this build "
                                f"(available: {', '.join(mi.variants())})")
    if not (name.startswith("llvm_ad_") or name.startswith("cuda_ad_")):
        raise pytest.UsageError(f"--variant {name}: mi-gaussians needs a JIT variant with AD (llvm_ad_*, cuda_ad_*)")
    try:
        mi.set_variant(name)
    except Exception as e:    # e.g. cuda_ad_rgb on a machine without a CUDA device
        raise pytest.UsageError(f"--variant {name}: cannot be selected here ({e})") from None


@pytest.fixture(scope="session", autouse=True)
def variant(request) -> str:
    """The variant of this run (``--variant``), selected for every test."""
    import mitsuba as mi

    name = request.config.getoption("--variant")
    mi.set_variant(name)
    return name


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


@pytest.fixture(scope="session")
def ray_cluster():
    """One local Ray cluster for the session (2 CPUs, as CI has): its address, for ``mi-gs ... --address``; this
    process is connected to it too. Shut down when the session ends, however it ends."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install '.[test]' brings it)")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


@pytest.fixture
def ordered_sums():
    """On the LLVM backend, Dr.Jit on one thread: with two, which thread takes which half of a kernel's lanes varies
    from run to run, and with it the order in which the backward pass sums a Gaussian's contributions (its float
    rounding); on one thread two runs of the same sums agree bit for bit. CUDA's atomics have no such switch: there
    the fixture changes nothing."""
    import drjit as dr
    import mitsuba as mi

    if dr.backend_v(mi.Float) != dr.JitBackend.LLVM:
        yield
        return
    before = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(before)
