"""``Gaussians``: the raw parameters of a 3DGS model as Dr.Jit tensors, nothing else.

Raw values are stored exactly as in a 3DGS ``point_cloud.ply`` (see ``docs/conventions.md``)::

    means      (N, 3)        world-space centres
    scales     (N, 3)        log standard deviations (sigma = exp(scale))
    rotations  (N, 4)        unnormalized quaternions, (w, x, y, z)
    opacities  (N,)          logits (alpha = sigmoid(opacity))
    sh_dc      (N, 3)        degree-0 SH coefficient per RGB channel
    sh_rest    (N, K - 1, 3) higher bands, coefficient-major (band index, then RGB); K = (degree + 1)^2

This class holds them, checks their shapes and converts them to and from NumPy, PLY files (:mod:`.ply`) and point
clouds (:mod:`.init`, one way). Activations (``exp``, ``sigmoid``, SH) are applied by the rasterizer
(:mod:`mi_gaussians.raster.projection`); the optimizer and densification live in :mod:`mi_gaussians.optim`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from ..conventions import sh_degree_from_coeff_count
from ..drjit_utils import owned_tensor, to_numpy

#: The raw parameters' names, in canonical order: the one list of them (``numpy()`` keys, the optimizer's groups).
PARAMETER_NAMES = ("means", "scales", "rotations", "opacities", "sh_dc", "sh_rest")


@dataclass
class Gaussians:
    means: "mi.TensorXf"
    scales: "mi.TensorXf"
    rotations: "mi.TensorXf"
    opacities: "mi.TensorXf"
    sh_dc: "mi.TensorXf"
    sh_rest: "mi.TensorXf"

    def __post_init__(self):
        n = self.means.shape[0] if len(self.means.shape) else 0
        expect = {"means": (n, 3), "scales": (n, 3), "rotations": (n, 4), "opacities": (n,), "sh_dc": (n, 3)}
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Gaussians.{name}: expected shape {shape}, got {got}")
        rest = tuple(self.sh_rest.shape)
        if len(rest) != 3 or rest[0] != n or rest[2] != 3:
            raise ValueError(f"Gaussians.sh_rest: expected shape ({n}, K-1, 3), got {rest}")
        sh_degree_from_coeff_count(rest[1] + 1)

    # ---------------------------------------------------------------- construction / conversion
    @classmethod
    def from_numpy(cls, means, scales, rotations, opacities, sh_dc, sh_rest=None) -> "Gaussians":
        means = np.asarray(means, dtype=np.float32).reshape(-1, 3)
        n = means.shape[0]
        if sh_rest is None:
            sh_rest = np.zeros((n, 0, 3), np.float32)
        sh_rest = np.asarray(sh_rest, np.float32)
        if sh_rest.ndim != 3:  # flat input; (N, K - 1, 3) input is kept as is (reshape(n, -1, 3) fails for N = 0)
            sh_rest = sh_rest.reshape(n, -1, 3)
        return cls(
            means=owned_tensor(means),
            scales=owned_tensor(np.asarray(scales, np.float32).reshape(n, 3)),
            rotations=owned_tensor(np.asarray(rotations, np.float32).reshape(n, 4)),
            opacities=owned_tensor(np.asarray(opacities, np.float32).reshape(n)),
            sh_dc=owned_tensor(np.asarray(sh_dc, np.float32).reshape(n, 3)),
            sh_rest=owned_tensor(sh_rest),
        )

    def numpy(self) -> dict[str, np.ndarray]:
        """Float32 NumPy copies of the raw parameters, keyed by :data:`PARAMETER_NAMES`."""
        return {name: to_numpy(getattr(self, name)).reshape(tuple(getattr(self, name).shape))
                for name in PARAMETER_NAMES}

    @property
    def n(self) -> int:
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.n

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeff_count(int(self.sh_rest.shape[1]) + 1)

    # ---------------------------------------------------------------- I/O and initialization
    @classmethod
    def load_ply(cls, path: str | os.PathLike) -> "Gaussians":
        """A 3DGS PLY as a model to render: NaN/Inf values and colours that would render Inf are refused."""
        from .ply import read_ply

        return cls.from_numpy(**read_ply(path, renderable=True))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Gaussians":
        """A model from a ``.ply`` (as :meth:`load_ply`), ``.splat``, ``.spz``, ``.glb`` or ``.gltf`` file (by the
        suffix; see :mod:`.web_formats`)."""
        from .web_formats import read_model

        return cls.from_numpy(**read_model(path)[0])

    def save_ply(self, path: str | os.PathLike) -> None:
        from .ply import write_ply

        write_ply(path, **self.numpy())

    @classmethod
    def from_points(cls, xyz, rgb, sh_degree: int = 3, initial_opacity: float = 0.1,
                    scale_factor: float = 1.0) -> "Gaussians":
        from .init import init_from_points

        return cls.from_numpy(**init_from_points(xyz, rgb, sh_degree=sh_degree, initial_opacity=initial_opacity,
                                                 scale_factor=scale_factor))
