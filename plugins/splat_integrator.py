"""The ``gaussian_splatting`` integrator: Mitsuba's ``mi.render`` through the tile-sorted rasterizer."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_gaussians.config import RasterConfig
from mi_gaussians.conventions import ELLIPSOID_STRUCT_SIZE, sh_coeff_count, sh_degree_from_coeff_count
from mi_gaussians.data.camera import Camera
from mi_gaussians.drjit_utils import fmax
from mi_gaussians.imwrite import SRGB_DECODE_THRESHOLD, SRGB_GAMMA, SRGB_OFFSET, SRGB_SLOPE
from mi_gaussians.raster.projection import GaussianArrays
from mi_gaussians.raster.rasterize import render_arrays

from .contract import ANTIALIASED, BACKGROUND, COLOR_SPACE, COLOR_SPACES, DEPTH_AOV, INTEGRATOR, SH_DEGREE


def gaussians_from_ellipsoids(shape, max_degree: int = 3) -> GaussianArrays:
    """Activated Gaussians from a Mitsuba ``ellipsoids`` shape, read through ``mi.traverse`` (AD-attached).

    The shape stores centres, sigmas, normalized (x, y, z, w) quaternions, opacities in (0, 1) and SH coefficients
    coefficient-major and RGB-interleaved with the DC term first (see ``mi_gaussians.conventions``)."""
    p = mi.traverse(shape)
    data, opac, sh = p["data"], p["opacities"], p["sh_coeffs"]
    n = dr.width(opac)
    if n == 0 or dr.width(data) != n * ELLIPSOID_STRUCT_SIZE:
        raise ValueError(f"gaussian_splatting: ellipsoids shape {shape.id()!r} holds {dr.width(data)} data values "
                         f"for {n} opacities (expected {ELLIPSOID_STRUCT_SIZE} per ellipsoid)")
    k, extra = divmod(dr.width(sh), 3 * n)
    try:
        stored_degree = sh_degree_from_coeff_count(k) if extra == 0 else None
    except ValueError:
        stored_degree = None
    if stored_degree is None:
        raise ValueError(f"gaussian_splatting: ellipsoids shape {shape.id()!r} has {dr.width(sh)} SH values for "
                         f"{n} ellipsoids (expected 3 (d + 1)^2 per ellipsoid, d <= 3)")
    degree = min(stored_degree, max_degree)
    idx = dr.arange(mi.UInt32, n)
    base = idx * ELLIPSOID_STRUCT_SIZE
    f = [dr.gather(mi.Float, data, base + c) for c in range(ELLIPSOID_STRUCT_SIZE)]
    rest = [dr.gather(mi.Vector3f, sh, idx * k + j) for j in range(1, sh_coeff_count(degree))]
    return GaussianArrays(means=mi.Point3f(f[0], f[1], f[2]), sigmas=mi.Vector3f(f[3], f[4], f[5]),
                          quats=mi.Vector4f(f[9], f[6], f[7], f[8]), opacity=mi.Float(opac),
                          sh_dc=dr.gather(mi.Vector3f, sh, idx * k), sh_rest=rest, sh_degree=degree)


def srgb_to_linear(x: mi.Float) -> mi.Float:
    """The sRGB transfer function inverted (differentiable; the power curve continues above 1): the Dr.Jit twin of
    :func:`mi_gaussians.imwrite.srgb_to_linear`, with its constants."""
    return dr.select(x <= SRGB_DECODE_THRESHOLD, x / SRGB_SLOPE,
                     dr.power((fmax(x, SRGB_DECODE_THRESHOLD) + SRGB_OFFSET) / (1.0 + SRGB_OFFSET), SRGB_GAMMA))


def _concat(parts: list[GaussianArrays]) -> GaussianArrays:
    if len(parts) == 1:
        return parts[0]
    deg = min(p.sh_degree for p in parts)
    cat = dr.concat
    return GaussianArrays(
        means=mi.Point3f(*[cat([p.means[i] for p in parts]) for i in range(3)]),
        sigmas=mi.Vector3f(*[cat([p.sigmas[i] for p in parts]) for i in range(3)]),
        quats=mi.Vector4f(*[cat([p.quats[i] for p in parts]) for i in range(4)]),
        opacity=cat([p.opacity for p in parts]),
        sh_dc=mi.Vector3f(*[cat([p.sh_dc[i] for p in parts]) for i in range(3)]),
        sh_rest=[mi.Vector3f(*[cat([p.sh_rest[j][i] for p in parts]) for i in range(3)])
                 for j in range(sh_coeff_count(deg) - 1)],
        sh_degree=deg)


class GaussianSplattingIntegrator(mi.CppADIntegrator):
    r"""
    .. _integrator-gaussian_splatting:

    Gaussian splatting (:monosp:`gaussian_splatting`)
    -------------------------------------------------

    .. pluginparameters::

     * - background
       - |float| or |rgb|
       - Colour seen where the Gaussians leave transmittance; it is not an emitter. (Default: 0)

     * - sh_degree
       - |int|
       - Active spherical-harmonics degree; -1 uses every band the shapes store. (Default: -1)

     * - depth_aov
       - |bool|
       - Append the expected depth (camera-space z, 0 where nothing was hit) as the last channel. (Default: false)

     * - color_space
       - |string|
       - What the Gaussians' colours are: ``linear`` radiance, or ``srgb``-encoded values (3DGS models fitted to
         photographs, and ``mi-gs optimize scene.xml`` models without ``--linear``), which are decoded to linear
         radiance after blending (background included) so that the film holds radiance. (Default: ``linear``)

     * - antialiased
       - |bool|
       - Mip-Splatting's 2D filter (gsplat's ``antialiased`` mode): each Gaussian's opacity is scaled by
         sqrt(det(S) / det(S + 0.3 I)) of its 2D covariance S. A model trained with ``mi-gs optimize --antialiased``
         must be rendered with it (its ``gaussians.xml`` says so). (Default: false)

    Rasterizes the 3D Gaussians of every ``ellipsoids`` shape in the scene (a 3DGS ``point_cloud.ply`` loaded by
    Mitsuba's own ``ellipsoids`` shape) with the tile-sorted, front-to-back alpha blending of Kerbl et al. 2023
    (16 x 16 tiles, EWA projection with the 0.3 low-pass dilation, alpha <= 0.99, early termination at T < 1e-4).
    The same scene renders with Mitsuba's ray tracer by switching the integrator to ``volprim_rf_basic``.

    The sensor must be a ``perspective`` camera (field of view, principal point offsets and film size are honoured).
    The output has the film's base channels: RGB, plus alpha when the film's ``pixel_format`` is ``rgba``, plus the
    depth AOV when requested. ``mi.render(scene, params=params)`` is differentiable: ``dr.backward`` on a loss fills
    the gradients of the shapes' ``<id>.data``, ``<id>.opacities`` and ``<id>.sh_coeffs`` entries. Rendering reads
    those entries directly, so an optimization step never waits for the ray-tracing acceleration structure.

    .. tabs::

        .. code-tab:: xml

            <integrator type="gaussian_splatting">
                <rgb name="background" value="1, 1, 1"/>
            </integrator>
            <shape type="ellipsoids" id="gaussians">
                <string name="filename" value="point_cloud.ply"/>
            </shape>

        .. code-tab:: python

            'integrator': {'type': 'gaussian_splatting', 'background': mi.ScalarColor3f(1, 1, 1)},
            'gaussians': {'type': 'ellipsoids', 'filename': 'point_cloud.ply'},
    """

    def __init__(self, props):
        super().__init__(props)
        bg = props.get(BACKGROUND, 0.0)
        if isinstance(bg, (int, float)):
            self.background = (float(bg),) * 3
        else:
            c = mi.ScalarColor3f(bg)
            self.background = (float(c[0]), float(c[1]), float(c[2]))
        self.sh_degree = int(props.get(SH_DEGREE, -1))
        if self.sh_degree < -1 or self.sh_degree > 3:
            raise ValueError(f"gaussian_splatting: sh_degree must be -1 or in 0..3, got {self.sh_degree}")
        self.depth_aov = bool(props.get(DEPTH_AOV, False))
        self.color_space = str(props.get(COLOR_SPACE, "linear"))
        if self.color_space not in COLOR_SPACES:
            raise ValueError(f"gaussian_splatting: color_space must be 'linear' or 'srgb', got {self.color_space!r}")
        self.cfg = RasterConfig(antialiased=bool(props.get(ANTIALIASED, False)))

    # ------------------------------------------------------------------ helpers
    def _gaussians(self, scene) -> GaussianArrays:
        shapes = [s for s in scene.shapes() if s.is_ellipsoids()]
        if not shapes:
            raise ValueError("gaussian_splatting: the scene has no 'ellipsoids' shape holding Gaussians")
        max_deg = 3 if self.sh_degree < 0 else self.sh_degree
        return _concat([gaussians_from_ellipsoids(s, max_deg) for s in shapes])

    @staticmethod
    def _sensor(scene, sensor):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        film = sensor.film()
        if tuple(film.crop_size()) != tuple(film.size()) or tuple(film.crop_offset()) != (0, 0):
            raise ValueError("gaussian_splatting: film crop windows are not supported")
        return sensor

    def _image(self, scene, sensor) -> mi.TensorXf:
        cam = Camera.from_mitsuba(sensor)
        out = render_arrays(self._gaussians(scene), cam, self.background, self.cfg)
        rgb = out.rgb
        if self.color_space == "srgb":
            rgb = mi.TensorXf(srgb_to_linear(rgb.array), rgb.shape)
        chans = [rgb]
        if sensor.film().base_channels_count() >= 4:
            chans.append(out.alpha)
        if self.depth_aov:
            chans.append(out.depth)
        if len(chans) == 1:
            return rgb
        H, W = cam.height, cam.width
        flat = [dr.gather(mi.Float, rgb.array, dr.arange(mi.UInt32, H * W) * 3 + c) for c in range(3)]
        flat += [t.array for t in chans[1:]]
        n = len(flat)
        buf = dr.zeros(mi.Float, H * W * n)
        idx = dr.arange(mi.UInt32, H * W) * n
        for c, v in enumerate(flat):
            dr.scatter(buf, v, idx + c)
        return mi.TensorXf(buf, (H, W, n))

    # ------------------------------------------------------------------ Mitsuba interface
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not develop:
            raise ValueError("gaussian_splatting: develop=False is not supported (there is no film block)")
        with dr.suspend_grad():
            return self._image(scene, self._sensor(scene, sensor))

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        raise NotImplementedError("gaussian_splatting: forward-mode differentiation is not implemented; "
                                  "use reverse mode (dr.backward)")

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        sensor = self._sensor(scene, sensor)
        with dr.resume_grad():
            image = self._image(scene, sensor)
            dr.set_grad(image, grad_in)
            dr.enqueue(dr.ADMode.Backward, image)
            dr.traverse(dr.ADMode.Backward)

    def aov_names(self):
        return ["depth"] if self.depth_aov else []

    def to_string(self):
        return (f"GaussianSplattingIntegrator[background={self.background}, sh_degree={self.sh_degree}, "
                f"depth_aov={self.depth_aov}, color_space={self.color_space!r}, antialiased={self.cfg.antialiased}]")


def register() -> list[str]:
    mi.register_integrator(INTEGRATOR, lambda props: GaussianSplattingIntegrator(props))
    return [INTEGRATOR]
