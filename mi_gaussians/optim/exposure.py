"""Per-image exposure compensation (``--exposure affine``, the 2024 reference's ``--train_test_exp``).

Phone and camera captures change exposure and white balance from frame to frame. Each training image ``i`` gets an
affine colour transform ``E_i`` (3 x 4), applied to the rendered image before the loss: a rendered colour ``c`` (a
row vector) becomes ``c @ E_i[:, :3] + E_i[:, 3]`` (the reference's ``rendered.permute(1, 2, 0) @ E[:3, :3] +
E[:3, 3]``). The transforms start at the identity, so the first iterations are those of a run without them.

Unlike the reference, each step holds the transforms' mean at the identity (each matrix moved by the same amount
after Adam's step): a transform shared by every image could as well live in the model's colours, and without this
the two drift together (measured on mi_objects/colmap, 7k: -3.8 dB on the held-out views rendered as they are, which
see no transform; -1.0 dB with the mean held). The model keeps the images' mean exposure.

Unlike the reference too, a step moves only the transform of the image it rendered (Adam with ``mask_updates``, the
semantics of PyTorch's ``SparseAdam``): each step sees one training view, so only that image's transform has a gradient,
and a dense Adam's momentum would keep moving every other image's transform, after each visit, in the direction of a
gradient it no longer has (with 100 images and random gradients, a visit moves a transform by 7.5 times the learning
rate with a dense Adam, 0.8 times with the sparse one). Measured on mi_objects/colmap (7k, nothing to compensate): the
half-image score ties the plain run with it (35.69 against 35.70 dB; 35.25 with a dense Adam).

The transforms belong to the images, not to the scene: the model (the PLY, the exports) never holds them;
``exposure.json`` in the run folder does, name -> 3 x 4 matrix, as the reference writes it.

:class:`Exposure` owns them as :class:`~.adam.GaussianAdam` owns the Gaussians: its own ``mi.ad.Adam`` (PyTorch's
defaults, as the reference's ``torch.optim.Adam([self._exposure])``: eps 1e-8, betas 0.9 / 0.999; sparse, above), the
learning rate decaying from ``exposure_lr_init`` to ``exposure_lr_final`` over the run (``iterations``); a PyTree for
``dr.freeze``; checkpointed with the run. :func:`mi_gaussians.metrics.fit_affine` is the evaluation side: the transform
that best maps a render onto an image (least squares), to score test views the way the reference does (fitted on one
half, scored on the other).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import OptimConfig
from ..drjit_utils import owned_array
from .adam import export_state, finite_state, import_state, masked_step, opaque_step_counts
from .schedules import expon_lr

KEY = "exposure"
IDENTITY = np.eye(3, 4, dtype=np.float32).reshape(12)


def transform(c: "mi.Vector3f", e: list) -> "mi.Vector3f":
    """Colours ``c`` through the 3 x 4 transform ``e`` (12 values, row-major: ``E[r][col] = e[4 r + col]``):
    ``c @ E[:, :3] + E[:, 3]``."""
    return mi.Vector3f(*[c.x * e[j] + c.y * e[4 + j] + c.z * e[8 + j] + e[4 * j + 3] for j in range(3)])


class Exposure:
    """The affine colour transforms of ``n_images`` training images (see the module docstring)."""

    DRJIT_STRUCT = {"_adam": object}

    def __init__(self, n_images: int, cfg: OptimConfig = OptimConfig()):
        self.n = int(n_images)
        self.cfg = cfg
        self._adam = mi.ad.Adam(lr=0.0, epsilon=1e-8, mask_updates=True)
        identity = np.tile(IDENTITY, (self.n, 1))
        self._adam[KEY] = mi.TensorXf(owned_array(mi.Float, identity), (self.n, 12))
        self._adam.set_learning_rate({KEY: float(cfg.exposure_lr_init)})
        opaque_step_counts(self._adam, [KEY])

    @property
    def tensor(self) -> "mi.TensorXf":
        """The (n, 12) parameters: row i is ``E_i`` (3 x 4, row-major), grad-enabled."""
        return self._adam[KEY]

    def matrices(self) -> np.ndarray:
        """(n, 3, 4) float32, a host copy."""
        return np.array(self.tensor, dtype=np.float32).reshape(self.n, 3, 4)

    def per_image(self) -> np.ndarray:
        """What each image's colours go through: :meth:`matrices` (the interface of
        :meth:`.bilateral.BilateralGrids.per_image`)."""
        return self.matrices()

    def apply(self, rgb: "mi.TensorXf", index) -> "mi.TensorXf":
        """``rgb`` (H, W, 3) through the transform of image ``index`` (an int, or a 1-element ``mi.UInt32``, opaque
        inside a frozen step), differentiable in both."""
        if not dr.is_array_v(index):
            index = dr.opaque(mi.UInt32, int(index), 1)
        flat = self.tensor.array
        e = [dr.gather(mi.Float, flat, index * 12 + k) for k in range(12)]
        return mi.TensorXf(dr.ravel(transform(dr.unravel(mi.Vector3f, rgb.array), e)), tuple(rgb.shape))

    def regularization(self, index) -> None:
        """No regularizer (the bilateral grids' interface: :meth:`.bilateral.BilateralGrids.regularization`)."""
        return None

    def learning_rate(self, step: int) -> float:
        """The rate at the 1-based iteration ``step``: decaying over the run's schedule, as the positions'."""
        o = self.cfg
        return expon_lr(step, o.exposure_lr_init, o.exposure_lr_final, o.position_lr_max_steps)

    def set_learning_rate(self, lr) -> None:
        """A Python float, or a 1-element ``mi.Float`` (inside a frozen step)."""
        self._adam.set_learning_rate({KEY: lr if dr.is_array_v(lr) else float(lr)})

    def step(self, active=None) -> None:
        """One Adam step from the gradient of the last backward pass (masked by ``active``, as the Gaussians'), then
        the transforms moved so that their mean is the identity (see the module docstring)."""
        masked_step(self._adam, [KEY], active)
        t = self._adam[KEY]
        identity = dr.select(dr.arange(mi.UInt32, 12) % 5 == 0, 1.0, 0.0)     # E[r][r] = e[5 r]  (no host copy:
        self._adam[KEY] = t - dr.mean(t, axis=0) + mi.TensorXf(identity, (12,))  # the step may be frozen)

    # ------------------------------------------------------------------ checkpoints
    def finite(self) -> dict[str, "mi.Bool"]:
        """Whether the values and Adam moments are all finite (a 1-element device flag)."""
        return {"exposure": finite_state(self._adam, [KEY])[KEY]}

    def export(self) -> dict[str, np.ndarray]:
        """The transforms and their Adam state, for a checkpoint (``value``, ``exposure.t/m/v``)."""
        return {"value": np.array(self.tensor, dtype=np.float32).reshape(self.n, 12),
                **export_state(self._adam, [KEY])}

    def restore(self, arrays: dict) -> None:
        """What :meth:`export` wrote (KeyError / ValueError when it does not fit: another number of images)."""
        value = np.asarray(arrays["value"], np.float32)
        if value.shape != (self.n, 12):
            raise ValueError(f"saved exposure transforms of shape {value.shape}, the run has {self.n} images")
        self._adam[KEY] = mi.TensorXf(owned_array(mi.Float, value), (self.n, 12))   # (same shape: state kept)
        import_state(self._adam, [KEY], arrays)
