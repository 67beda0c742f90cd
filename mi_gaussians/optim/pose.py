"""Camera pose optimisation (``--pose-opt``): each training camera gets a learnt rigid correction, gsplat's ``pose_opt``.

Real captures come with imperfect poses, and a fraction of a degree blurs every Gaussian. As gsplat's
``CameraOptModule``, training camera ``i`` carries 9 numbers ``p_i``, zero at the start: a translation ``dx`` and a
rotation in the continuous 6D form of Zhou et al. 2019 (``rotation_6d``: the first two rows of a rotation matrix,
Gram-Schmidt-orthonormalised; the 6 numbers are added to the identity's ``(1, 0, 0, 0, 1, 0)``). The corrected
camera-to-world matrix is ``C2W @ [[rot, dx], [0, 1]]``: a rotation about the camera's centre and a translation, both
in the camera's own axes. Unlike gsplat, ``dx`` is ``p[0:3]`` times the scene extent (gsplat normalises its scenes to
about unit size first), so the learning rate means the same motion at every scene scale.

Where the rotation turns the camera (``optim.pose_opt_pivot``): about its centre (``"centre"``, gsplat's), or about a
point ahead of it on its axis, at the depth of the scene it sees (``"depth"``, :func:`pivot_depths`; the correction is
then ``C2W @ T(q) @ [[rot, dx], [0, 1]] @ T(-q)``, ``q = (0, 0, pivot)``). The choice matters to Adam, not to what
the corrections can reach: a turn about the centre and a sideways move both shift the image of a distant object, so
about the centre the loss's steep direction (the image shift) mixes rotation and translation and its flat one (the
pair that keeps the object in place, told apart only by parallax) mixes them too, and Adam, which scales each number
on its own, zigzags across the valley instead of following it. Turned about a point at the scene's depth, a rotation
leaves that point where it was in the image and moves nearer and farther points against each other (parallax alone),
while the translation shifts the image; at the pivot depth ``sum(1/z) / sum(1/z^2)`` over the points a camera sees,
the two image motions are uncorrelated, so the valley lies along the rotation's own numbers, which Adam scales on
their own (measured in the README: more of a known rotation error is undone in the same number of steps).

Gradients: the rasterizer's projection is Dr.Jit arithmetic of the view's rotation ``R``, translation ``t`` and
centre, and the blend's hand-written backward pass feeds it; built from ``p_i`` by :func:`adjusted_view`, the view
passes the gradient on to ``p_i`` (``tests/test_pose.py`` checks it against float64 finite differences of the
independent reference renderer).

:class:`PoseDeltas` owns them as :class:`~.exposure.Exposure` owns the colour transforms: its own ``mi.ad.Adam``
(PyTorch's eps 1e-8; gsplat's L2 weight decay 1e-6, ``optim.pose_opt_reg``), sparse (a step moves only the rendered
camera's ``p_i``, its L2 term included: each step sees one view), at the rate ``optim.pose_opt_lr`` (constant unless
``optim.pose_opt_lr_decay`` is set: then moving exponentially to that factor times it, an input of the frozen step
like the positions' rate). gsplat's dense Adam at 1e-5 keeps moving every camera between its visits with the
momentum of its last gradient; a sparse step
moves a camera only on its own visits, about one step in N for N training images, so our default is ten times
gsplat's rate (measured on mi_objects/colmap -r 2 with every camera turned by 1 degree and moved by 1 % of the scene:
1e-5, 1e-4, 3e-4 and 1e-3 left 0.86, 0.39, 0.32 and 0.30 degrees and scored 23.96, 28.13, 27.19 and 24.44 dB
at 7k, against 21.70 without --pose-opt and 35.97 with exact cameras; README). A PyTree for
``dr.freeze`` (the view index is an input of the frozen step, so it keeps replaying), checkpointed with the run. Test
cameras are never corrected (gsplat's and nerfstudio's protocol): what the corrections learn belongs to the training
images, and the run folder holds them as refined cameras (``cameras_refined.json``, ``images_refined.txt``).
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import OptimConfig
from ..data.camera import Camera
from ..drjit_utils import owned_array
from ..raster.projection import ViewParams
from .adam import export_state, finite_state, import_state, masked_step, opaque_step_counts
from .schedules import expon_lr

KEY = "pose"
WIDTH = 9                                      # dx (3), the 6D rotation's offset from the identity (6)
IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def adjusted_view(view: ViewParams, p: list, extent: float, pivot=0.0) -> ViewParams:
    """``view`` moved by the correction ``p`` (9 Dr.Jit scalars; see the module docstring), its rotation about the point
    ``pivot`` ahead of the camera on its axis (a depth: a Python float or a Dr.Jit scalar; 0: about the centre, gsplat's),
    differentiable in ``p``: with ``d = dx + pivot (e_z - rot e_z)``, ``R' = rot^T R``, ``t' = rot^T (t - d)``, centre
    ``+ R^T d``."""
    a1 = mi.Vector3f(*[p[3 + k] + IDENTITY_6D[k] for k in range(3)])
    a2 = mi.Vector3f(*[p[6 + k] + IDENTITY_6D[3 + k] for k in range(3)])
    b1 = dr.normalize(a1)
    b2 = dr.normalize(a2 - dr.dot(b1, a2) * b1)
    b3 = dr.cross(b1, b2)
    # the camera-axes translation: dx, plus what keeps the pivot (0, 0, pivot) fixed under the rotation (rows b1..b3)
    dx = [p[k] * extent + pivot * ((1.0 if k == 2 else 0.0) - b[2]) for k, b in enumerate((b1, b2, b3))]
    R = view.R
    rows = [b1[i] * R[0] + b2[i] * R[1] + b3[i] * R[2] for i in range(3)]      # row i of rot^T R
    u = view.t - mi.Vector3f(*dx)
    t = mi.Vector3f(*[b1[i] * u[0] + b2[i] * u[1] + b3[i] * u[2] for i in range(3)])
    center = view.center + dx[0] * R[0] + dx[1] * R[1] + dx[2] * R[2]
    return dataclasses.replace(view, R=mi.Matrix3f([[r[0], r[1], r[2]] for r in rows]), t=t,
                               center=mi.Point3f(center))


def adjusted_world_to_camera(world_to_camera: np.ndarray, p: np.ndarray, extent: float,
                             pivot: float = 0.0) -> np.ndarray:
    """The (4, 4) float64 world-to-camera matrix of a camera corrected by ``p`` (9 numbers) about ``pivot``, as
    :func:`adjusted_view`."""
    p = np.asarray(p, np.float64)
    a1, a2 = p[3:6] + IDENTITY_6D[:3], p[6:9] + IDENTITY_6D[3:]
    b1 = a1 / np.linalg.norm(a1)
    b2 = a2 - b1 @ a2 * b1
    b2 /= np.linalg.norm(b2)
    rot = np.stack([b1, b2, np.cross(b1, b2)])
    fix = np.eye(4)
    fix[:3, :3], fix[:3, 3] = rot, p[:3] * extent + float(pivot) * (np.array([0.0, 0.0, 1.0]) - rot[:, 2])
    return np.linalg.inv(np.linalg.inv(np.asarray(world_to_camera, np.float64)) @ fix)


def pivot_depths(cameras: list[Camera], points: np.ndarray | None, centre: np.ndarray | None = None) -> np.ndarray:
    """Per camera, the depth on its axis about which its correction turns (``optim.pose_opt_pivot = "depth"``): of the
    scene points it sees (in front, inside the image), ``sum(1/z) / sum(1/z^2)``, the depth at which a turn's image
    motion and a sideways move's are uncorrelated over those points, so that the correction's rotation and translation
    are separate directions of the loss (module docstring); without points in view, the depth of ``centre`` (the
    scene's) on the axis when it lies ahead, else 0 (the camera's centre). (len(cameras),) float64."""
    pts = None if points is None or len(points) == 0 else np.asarray(points, np.float64)
    out = np.zeros(len(cameras))
    for i, cam in enumerate(cameras):
        if pts is not None:
            uv, z = cam.project(pts)
            seen = cam.sees(uv, z)
            if seen.any():
                inv = 1.0 / z[seen]
                out[i] = float(np.sum(inv) / np.sum(inv * inv))
                continue
        if centre is not None:
            out[i] = max(0.0, float(cam.project(centre)[1][0]))
    return out


class PoseDeltas:
    """The pose corrections of ``n_images`` training cameras in a scene of size ``extent`` (module docstring)."""

    DRJIT_STRUCT = {"_adam": object, "_pivots": object}

    def __init__(self, n_images: int, cfg: OptimConfig = OptimConfig(), extent: float = 1.0,
                 pivots: np.ndarray | None = None):
        self.n = int(n_images)
        self.extent = float(extent)
        # the depth each camera's rotation turns about (pivot_depths; 0: its centre); fixed for the run, checkpointed
        self._set_pivots(np.zeros(self.n) if pivots is None else pivots)
        self.weight_decay = float(cfg.pose_opt_reg)
        self._rates = (float(cfg.pose_opt_lr), float(cfg.pose_opt_lr_decay), int(cfg.position_lr_max_steps))
        self._adam = mi.ad.Adam(lr=float(cfg.pose_opt_lr), epsilon=1e-8, mask_updates=True)
        self._adam[KEY] = mi.TensorXf(dr.zeros(mi.Float, self.n * WIDTH), (self.n, WIDTH))
        opaque_step_counts(self._adam, [KEY])

    @property
    def tensor(self) -> "mi.TensorXf":
        """The (n, 9) corrections, grad-enabled."""
        return self._adam[KEY]

    def _set_pivots(self, pivots) -> None:
        pivots = np.asarray(pivots, np.float64).reshape(-1)
        if pivots.shape != (self.n,) or not np.all(np.isfinite(pivots)) or np.any(pivots < 0):
            raise ValueError(f"pose pivots: {self.n} finite depths >= 0 expected, got {pivots.shape} {pivots[:4]}")
        self.pivots = pivots.astype(np.float32).astype(np.float64)   # (as the frozen step's float32 copy holds them)
        self._pivots = owned_array(mi.Float, pivots.astype(np.float32))

    def deltas(self) -> np.ndarray:
        """(n, 9) float64, a host copy."""
        return np.array(self.tensor, dtype=np.float64).reshape(self.n, WIDTH)

    def view(self, view: ViewParams, index) -> ViewParams:
        """Training view ``index`` (an int, or a 1-element ``mi.UInt32``, opaque inside a frozen step) through its
        correction, differentiable in the correction."""
        if not dr.is_array_v(index):
            index = dr.opaque(mi.UInt32, int(index), 1)
        flat = self.tensor.array
        p = [dr.gather(mi.Float, flat, index * WIDTH + k) for k in range(WIDTH)]
        return adjusted_view(view, p, self.extent, dr.gather(mi.Float, self._pivots, index))

    def learning_rate(self, step: int) -> float:
        """The rate at the 1-based iteration ``step``: ``optim.pose_opt_lr`` decaying exponentially to
        ``optim.pose_opt_lr_decay`` times itself over the run's schedule (``position_lr_max_steps``); constant when
        that factor is 1 (or the rate 0)."""
        lr, decay, max_steps = self._rates
        if decay == 1.0 or lr == 0.0:
            return lr
        return expon_lr(step, lr, lr * decay, max_steps)

    def set_learning_rate(self, lr) -> None:
        """A Python float, or a 1-element ``mi.Float`` (inside a frozen step)."""
        self._adam.set_learning_rate({KEY: lr if dr.is_array_v(lr) else float(lr)})

    def step(self, index, active=None) -> None:
        """One Adam step of camera ``index``'s correction from the gradient of the last backward pass, its L2 weight
        decay (PyTorch's ``weight_decay``: ``grad += decay * p``) included; masked by ``active`` as the Gaussians'."""
        if not dr.is_array_v(index):
            index = dr.opaque(mi.UInt32, int(index), 1)
        t = self._adam[KEY]
        if self.weight_decay > 0:
            rows = dr.arange(mi.UInt32, self.n * WIDTH) // WIDTH
            decay = dr.select(rows == index, self.weight_decay * dr.detach(t.array), 0.0)
            dr.set_grad(t, mi.TensorXf(dr.grad(t).array + decay, (self.n, WIDTH)))
        masked_step(self._adam, [KEY], active)

    def cameras(self, cameras: list[Camera]) -> list[Camera]:
        """``cameras`` (the training cameras, in order) through their corrections (float64)."""
        deltas = self.deltas()
        return [dataclasses.replace(c, world_to_camera=adjusted_world_to_camera(c.world_to_camera, d, self.extent, z))
                for c, d, z in zip(cameras, deltas, self.pivots)]

    # ------------------------------------------------------------------ checkpoints
    def finite(self) -> dict[str, "mi.Bool"]:
        """Whether the values and Adam moments are all finite (a 1-element device flag)."""
        return {"pose": finite_state(self._adam, [KEY])[KEY]}

    def export(self) -> dict[str, np.ndarray]:
        """The corrections, their pivots and their Adam state, for a checkpoint (``value``, ``pivot``, ``pose.t/m/v``)."""
        return {"value": np.array(self.tensor, dtype=np.float32).reshape(self.n, WIDTH), "pivot": self.pivots.copy(),
                **export_state(self._adam, [KEY])}

    def restore(self, arrays: dict) -> None:
        """What :meth:`export` wrote (KeyError / ValueError when it does not fit: another number of images). The saved
        pivots replace the run's, as the corrections mean moves about them (a checkpoint without them, from before
        pivots existed, turned its cameras about their centres)."""
        value = np.asarray(arrays["value"], np.float32)
        if value.shape != (self.n, WIDTH):
            raise ValueError(f"saved pose corrections of shape {value.shape}, the run has {self.n} training cameras")
        self._set_pivots(arrays["pivot"] if "pivot" in arrays else np.zeros(self.n))
        self._adam[KEY] = mi.TensorXf(owned_array(mi.Float, value), (self.n, WIDTH))   # (same shape: state kept)
        import_state(self._adam, [KEY], arrays)


def save_refined_cameras(out, cameras: list[Camera]) -> None:
    """The refined training cameras into the run folder ``out``: ``cameras_refined.json`` (``{"train": [...]}``, the
    camera JSON of ``mi-gs render --camera``) and ``images_refined.txt`` (COLMAP's ``images.txt``, one camera id per
    distinct intrinsics, in order of appearance), each written atomically."""
    import json
    from pathlib import Path

    from ..data.colmap import images_text
    from ..io_utils import atomic_write_text
    from ..run_folder import REFINED_CAMERAS, REFINED_IMAGES

    out = Path(out)
    atomic_write_text(out / REFINED_CAMERAS, json.dumps({"train": [c.to_dict() for c in cameras]}, indent=1) + "\n")
    ids: dict = {}
    cids = [ids.setdefault((c.width, c.height, c.fx, c.fy, c.cx, c.cy), len(ids) + 1) for c in cameras]
    atomic_write_text(out / REFINED_IMAGES, images_text([c.name for c in cameras],
                                                        [c.world_to_camera for c in cameras], cids))
