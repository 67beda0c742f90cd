"""Per-image bilateral grids (``--exposure bilateral``): gsplat's ``use_bilateral_grid``, from "Bilateral Guided
Radiance Field Processing" (Wang et al., SIGGRAPH 2024).

Where ``--exposure affine`` gives each training image one 3 x 4 colour transform, this gives it a grid of them over
(x, y, guidance): ``W x H x L`` cells (``optim.exposure_grid``, gsplat's 16 x 16 x 8). A rendered pixel with centre
``(u, v)`` in [0, 1]^2 and colour ``c`` takes the transform trilinearly interpolated at ``(u (W - 1), v (H - 1),
luma(c) (L - 1))``, ``luma`` the BT.601 weights (0.299, 0.587, 0.114) clamped to [0, 1] (gsplat's ``F.grid_sample``
with ``align_corners=True`` and border padding), and becomes ``c @ E[:, :3] + E[:, 3]`` (the layout of
:mod:`.exposure`). So a transform can vary across the image (vignetting, a phone's local tone mapping) and with the
brightness (a tone curve), which one affine transform cannot. The interpolation is a chain of ``a + t (b - a)``, so
a grid of identical transforms (the start: the identity everywhere) changes no bit of the render.

As gsplat: Adam with eps 1e-15 over all the grids, a learning rate of 2e-3 (``optim.exposure_grid_lr``) warmed up from
1 % over the first 1,000 steps and then decaying to 1 % of it over the run, and a total-variation loss of all the
grids at every step (weight 10, ``optim.exposure_grid_tv``: per axis, the mean squared difference of neighbouring
cells of a grid, summed, averaged over the grids) that keeps them smooth. Unlike the affine transforms, the grids
step densely, as gsplat's: every grid has a gradient at every step (its total variation), and with gsplat's rate a
sparse step moved them less in a short run (known per-image gains, 2,400 steps: 14 % off sparse, 11 % dense).

As :mod:`.exposure`, and unlike gsplat, each step holds the grids' mean transform at the identity, the mean over the
images and over (x, y) at each guidance level: a transform common to all images at every position could as well
live in the model's colours (with it free, the two drift together, as measured for the affine transforms), while a
pattern across the image shared by all of them (a lens's vignetting), which no 3D model can absorb, stays free.

The grids belong to the images, not to the scene: ``exposure_grids.npz`` in the run folder holds them (``names``,
``grids`` of shape (n, L, H, W, 3, 4)); :func:`mi_gaussians.metrics.apply_bilateral` applies one with NumPy (the
viewer). Checkpointed with the run; a PyTree for ``dr.freeze``.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import OptimConfig
from ..drjit_utils import owned_array
from ..image_ops import LUMA
from .adam import export_state, finite_state, import_state, masked_step, opaque_step_counts
from .exposure import IDENTITY, transform
from .schedules import warmup_expon_lr

KEY = "grids"
WARMUP_STEPS, WARMUP_START = 1000, 0.01   # gsplat's rate (optim.exposure_grid_lr) warmed up from 1 % over 1,000
FINAL_FACTOR = 0.01                   # steps, then decaying exponentially to 1 % over the run
EPS = 1e-15                           # its Adam's epsilon


class BilateralGrids:
    """The bilateral grids of ``n_images`` training images (see the module docstring). Stored as one tensor of
    shape (L, n H W, 12): level, then (image, y, x), then the 3 x 4 transform row-major."""

    DRJIT_STRUCT = {"_adam": object}

    def __init__(self, n_images: int, cfg: OptimConfig = OptimConfig()):
        self.n = int(n_images)
        self.cfg = cfg
        self.width, self.height, self.levels = (int(s) for s in cfg.exposure_grid)
        if min(self.width, self.height, self.levels) < 2:
            raise ValueError(f"optim.exposure_grid: a bilateral grid needs at least 2 cells along each axis, "
                             f"got {cfg.exposure_grid}")
        self._adam = mi.ad.Adam(lr=0.0, epsilon=EPS)
        cells = self.levels * self.n * self.height * self.width
        self._adam[KEY] = mi.TensorXf(owned_array(mi.Float, np.tile(IDENTITY, cells)),
                                      (self.levels, self.n * self.height * self.width, 12))
        self._adam.set_learning_rate({KEY: 0.0})
        opaque_step_counts(self._adam, [KEY])

    @property
    def tensor(self) -> "mi.TensorXf":
        """The (L, n H W, 12) parameters, grad-enabled."""
        return self._adam[KEY]

    def grids(self) -> np.ndarray:
        """(n, L, H, W, 3, 4) float32, a host copy."""
        a = np.array(self.tensor, dtype=np.float32).reshape(self.levels, self.n, self.height, self.width, 3, 4)
        return np.ascontiguousarray(a.transpose(1, 0, 2, 3, 4, 5))

    def per_image(self) -> np.ndarray:
        """What each image's colours go through: :meth:`grids`."""
        return self.grids()

    def learning_rate(self, step: int) -> float:
        """gsplat's schedule at the 1-based iteration ``step`` of a run whose schedules span
        ``position_lr_max_steps``."""
        return warmup_expon_lr(step, self.cfg.exposure_grid_lr, WARMUP_STEPS, WARMUP_START, FINAL_FACTOR,
                               self.cfg.position_lr_max_steps)

    def _cell(self, index, x, y, z) -> "mi.UInt32":
        """Flat offset of the transform of cell (x, y, z) of image ``index``'s grid."""
        return ((z * self.n + index) * self.height + y) * self.width * 12 + x * 12

    def apply(self, rgb: "mi.TensorXf", index) -> "mi.TensorXf":
        """``rgb`` (H, W, 3) through the grid of image ``index`` (an int, or a 1-element ``mi.UInt32``, opaque
        inside a frozen step), differentiable in both (the guidance too, as ``grid_sample``'s)."""
        if not dr.is_array_v(index):
            index = dr.opaque(mi.UInt32, int(index), 1)
        h, w = int(rgb.shape[0]), int(rgb.shape[1])
        c = dr.unravel(mi.Vector3f, rgb.array)
        pixel = dr.arange(mi.UInt32, h * w)
        gx = (mi.Float(pixel % w) + 0.5) * ((self.width - 1) / w)
        gy = (mi.Float(pixel // w) + 0.5) * ((self.height - 1) / h)
        gz = dr.clip(LUMA[0] * c.x + LUMA[1] * c.y + LUMA[2] * c.z, 0.0, 1.0) * (self.levels - 1)
        (x0, fx), (y0, fy), (z0, fz) = (_split(g, n) for g, n in ((gx, self.width), (gy, self.height),
                                                                   (gz, self.levels)))
        flat = self.tensor.array

        def corner(dx, dy, dz):
            base = self._cell(index, x0 + dx, y0 + dy, z0 + dz)
            return [dr.gather(mi.Float, flat, base + k) for k in range(12)]

        def lerp(a, b, t):                  # a + t (b - a): exact where a == b
            return [ai + t * (bi - ai) for ai, bi in zip(a, b)]

        def along_x(dy, dz):
            return lerp(corner(0, dy, dz), corner(1, dy, dz), fx)

        e = lerp(lerp(along_x(0, 0), along_x(1, 0), fy), lerp(along_x(0, 1), along_x(1, 1), fy), fz)
        return mi.TensorXf(dr.ravel(transform(c, e)), tuple(rgb.shape))

    def regularization(self, index=None) -> "mi.Float":
        """gsplat's ``total_variation_loss`` of all the grids times ``optim.exposure_grid_tv``: per axis, the mean
        squared difference of neighbouring cells of a grid, summed, and averaged over the grids (``index``, the
        rendered image, is not needed: every grid is regularized at every step, as gsplat does)."""
        flat = self.tensor.array
        total = mi.Float(0.0)
        for axis in range(3):
            size = [self.width, self.height, self.levels]
            size[axis] -= 1                 # (cells with a neighbour along this axis)
            count = size[0] * size[1] * size[2] * 12
            i = dr.arange(mi.UInt32, count * self.n)
            image, i = i // count, i % count
            k, cell = i % 12, i // 12
            x, y, z = cell % size[0], (cell // size[0]) % size[1], cell // (size[0] * size[1])
            step = [(1, 0, 0), (0, 1, 0), (0, 0, 1)][axis]
            a = dr.gather(mi.Float, flat, self._cell(image, x, y, z) + k)
            b = dr.gather(mi.Float, flat, self._cell(image, x + step[0], y + step[1], z + step[2]) + k)
            total += dr.sum(dr.square(b - a)) / count
        return (float(self.cfg.exposure_grid_tv) / self.n) * total

    def set_learning_rate(self, lr) -> None:
        """A Python float, or a 1-element ``mi.Float`` (inside a frozen step)."""
        self._adam.set_learning_rate({KEY: lr if dr.is_array_v(lr) else float(lr)})

    def step(self, active=None) -> None:
        """One dense Adam step (every grid: see the module docstring) from the gradient of the last backward pass
        (masked by ``active``), then the grids moved so that their mean over the images and (x, y) is the identity
        at every level (module docstring)."""
        masked_step(self._adam, [KEY], active)
        t = self._adam[KEY]
        mean = dr.mean(t, axis=1)                                             # (L, 12)
        identity = dr.select(dr.arange(mi.UInt32, 12) % 5 == 0, 1.0, 0.0)    # (no host copy: may be frozen)
        self._adam[KEY] = t - mi.TensorXf(mean.array, (self.levels, 1, 12)) + mi.TensorXf(identity, (12,))

    # ------------------------------------------------------------------ checkpoints
    def finite(self) -> dict[str, "mi.Bool"]:
        """Whether the values and Adam moments are all finite (a 1-element device flag)."""
        return {"exposure": finite_state(self._adam, [KEY])[KEY]}

    def export(self) -> dict[str, np.ndarray]:
        """The grids, their layout (``layout``: n, L, H, W) and their Adam state, for a checkpoint (``value``,
        ``grids.t/m/v``)."""
        return {"value": np.array(self.tensor, dtype=np.float32), "layout": np.array(self._layout(), np.int64),
                **export_state(self._adam, [KEY])}

    def _layout(self) -> tuple[int, int, int, int]:
        return self.n, self.levels, self.height, self.width

    def restore(self, arrays: dict) -> None:
        """What :meth:`export` wrote (KeyError / ValueError when it does not fit: another number of images or
        another grid)."""
        layout = tuple(int(k) for k in np.asarray(arrays["layout"]).reshape(-1))
        if layout != self._layout():
            raise ValueError(f"saved bilateral grids of {layout[0]} images, {'x'.join(map(str, layout[:0:-1]))} "
                             f"cells; the run has {self.n} images, {self.width}x{self.height}x{self.levels}")
        value = np.asarray(arrays["value"], np.float32)
        shape = tuple(self.tensor.shape)
        if value.shape != shape:
            raise ValueError(f"saved bilateral grids of shape {value.shape}, the run has {shape}")
        self._adam[KEY] = mi.TensorXf(owned_array(mi.Float, value), shape)   # (same shape: state kept)
        import_state(self._adam, [KEY], arrays)


def _split(g: "mi.Float", n: int) -> tuple["mi.UInt32", "mi.Float"]:
    """Lower cell index (at most ``n - 2``) and fraction of grid coordinate ``g`` in [0, n - 1]."""
    i0 = dr.minimum(mi.UInt32(dr.detach(g)), n - 2)
    return i0, g - mi.Float(i0)
