"""Coarse-to-fine training (DashGaussian, Chen et al., CVPR 2025): the early iterations render and fit the training
images at a reduced resolution, rising to the full one by ``until``; what the images hold sets how.

Fitting the low frequencies of the images first needs few pixels. DashGaussian measures where the images' energy
lies: ``E(s)``, the sum of the magnitudes of the centred 2D Fourier spectrum (mean over a strided subset of the
training images, over colour channels) inside the central window of the spectrum's size divided by ``s``, is the
energy an image downsampled by ``s`` keeps. Then:

* the coarsest scale ``s_max`` is the largest ``s`` (at most :data:`MAX_SCALE`) at which every image keeps a quarter
  of its energy: a rule of the images' content, so the same scene at twice the image size starts at twice the
  scale (a rule in pixels would not);
* the energies between ``E(s_max)`` and the total are split into :data:`LEVELS` equal steps; level ``i`` begins at
  the iteration ``until * log(E_i / E_min) / log(E_total / E_min)`` (a log scale: the coarse levels, which carry
  most of the energy, get their share of the iterations) and its scale is the one that keeps ``E_i``;
* between two levels the number of pixels (``1 / s^2``) grows linearly, and an iteration renders at the integer
  scale ``floor(s)`` (DashGaussian's ``int(scale)``): a handful of image sizes per run, each a recording of the frozen
  step.

What changes at scale ``s``: each training camera becomes the same camera at ``round(W / s) x round(H / s)`` pixels
(its intrinsics scaled), and each target its area-average to that size (RGB, alpha, inverse depth). Scores are
always taken at full resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: DashGaussian's bounds: at most 8x fewer pixels per side, the energy split into 32 levels, a quarter of the
#: energy kept at the start.
MAX_SCALE = 8.0
LEVELS = 32
START_ENERGY = 0.25
#: images whose spectra are measured (evenly strided): the schedule is a property of the scene, not of each image
SAMPLED_IMAGES = 16


def _centred_magnitude(image: np.ndarray) -> np.ndarray:
    """|FFT| of an (H, W, C) image, centred, summed over channels."""
    im = np.asarray(image, np.float64)
    f = np.fft.fftshift(np.fft.fft2(im - im.mean(axis=(0, 1)), axes=(0, 1)), axes=(0, 1))
    return np.abs(f).sum(axis=2)


def window_energy(spectrum: np.ndarray, scale: float) -> float:
    """The energy inside the central window of ``spectrum``'s size divided by ``scale`` (at least one sample)."""
    h, w = spectrum.shape
    ch, cw = (h + 1) // 2, (w + 1) // 2
    hh, hw = max(int(h / scale) // 2, 0), max(int(w / scale) // 2, 0)
    return float(spectrum[ch - hh:ch + hh + 1, cw - hw:cw + hw + 1].sum())


def scale_keeping(spectrum: np.ndarray, energy: float, steps: int = 48) -> float:
    """The largest scale whose window keeps at least ``energy`` (bisection on 1 / scale)."""
    lo, hi = 0.0, 1.0                       # 1 / scale
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if mid > 0 and window_energy(spectrum, 1.0 / mid) < energy:
            lo = mid
        else:
            hi = mid
    return 1.0 / max(hi, 1e-9)


@dataclass(frozen=True)
class ResolutionSchedule:
    """Levels (begin iteration, scale), the first at iteration 0, and ``until``: full resolution from there on."""

    begins: tuple[int, ...]
    scales: tuple[float, ...]
    until: int

    def scale_at(self, step: int) -> int:
        """The integer downsampling factor of (1-based) iteration ``step``."""
        if step >= self.until or not self.begins:
            return 1
        i = max(k for k, b in enumerate(self.begins) if b <= step)
        if i + 1 >= len(self.begins):
            return max(1, int(self.scales[i]))
        b0, b1 = self.begins[i], self.begins[i + 1]
        t = (step - b0) / max(b1 - b0, 1)
        inv2 = (1.0 - t) / self.scales[i] ** 2 + t / self.scales[i + 1] ** 2
        return max(1, int(1.0 / math.sqrt(inv2)))

    def scales_used(self, iterations: int) -> list[int]:
        """The distinct scales of iterations 1..``iterations``, coarsest first."""
        return sorted({self.scale_at(s) for s in range(1, iterations + 1)}, reverse=True)

    def to_dict(self) -> dict:
        return {"begins": list(self.begins), "scales": [round(s, 4) for s in self.scales], "until": self.until}


def spectrum_schedule(images: list[np.ndarray], until: int) -> ResolutionSchedule:
    """DashGaussian's schedule of the training ``images`` ((H, W, C) arrays of one size class; see the module
    docstring), reaching full resolution at iteration ``until``."""
    if not images or until <= 0:
        return ResolutionSchedule((), (), 0)
    picked = images[::max(1, len(images) // SAMPLED_IMAGES)][:SAMPLED_IMAGES]
    spectra = [_centred_magnitude(im) for im in picked]
    s_max = MAX_SCALE
    for sp in spectra:
        s_max = min(s_max, scale_keeping(sp, START_ENERGY * float(sp.sum())))
    shape = spectra[0].shape
    mean = sum(sp for sp in spectra if sp.shape == shape) / sum(1 for sp in spectra if sp.shape == shape)
    total = float(mean.sum())
    e_min = window_energy(mean, s_max)
    if s_max <= 1.0 or not total > e_min > 0:
        return ResolutionSchedule((), (), 0)
    begins, scales = [], []
    span = math.log(total / e_min)
    for i in range(LEVELS):
        e = e_min + (total - e_min) * i / (LEVELS - 1)
        begins.append(int(until * math.log(e / e_min) / span))
        scales.append(s_max if i == 0 else 1.0 if i == LEVELS - 1 else min(s_max, scale_keeping(mean, e)))
    return ResolutionSchedule(tuple(begins), tuple(scales), int(until))


def scaled_size(width: int, height: int, scale: int) -> tuple[int, int]:
    """The image size of a camera of ``width`` x ``height`` at integer scale ``scale`` (at least 1 x 1)."""
    return max(1, round(width / scale)), max(1, round(height / scale))
