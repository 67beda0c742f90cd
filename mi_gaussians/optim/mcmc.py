"""MCMC densification (Kheradmand et al. 2024, "3D Gaussian Splatting as Markov Chain Monte Carlo") as a strategy.

    strategy = MCMCStrategy(cfg.mcmc, seed=...)        # TrainConfig.strategy = "mcmc", --strategy mcmc
    state = strategy.initialize_state(params.n)

The Gaussians are samples of a distribution; densification moves and adds samples instead of cloning and splitting
on gradient statistics, and the number of Gaussians never exceeds ``cap_max`` (``--max-gaussians``). Rules (the
paper, and gsplat's ``MCMCStrategy`` / ``relocate`` / ``sample_add`` / ``inject_noise_to_position``; ``step`` is the
1-based iteration, o = sigmoid(opacity), s = exp(scales))::

    when refine_start_iter < step < refine_stop_iter and step % refine_every == 0 (host work, Adam step skipped):
        relocate: every dead Gaussian (o <= min_opacity) becomes a copy of a live one drawn with probability
                  proportional to o (with replacement); a live Gaussian drawn k times is shared by N = k + 1 copies,
                  each with (Eq. 9 of the paper, :func:`relocation`)
                      o' = 1 - (1 - o)^(1/N)                        (N copies in a row let o through: opacity kept)
                      s' = s * o / sum_{i=1..N} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)
                  o' clamped to [min_opacity, 1 - 2^-23]; N at most 50 (gsplat's table)
        add:      n_new = min(cap_max, floor((1 + growth) n)) - n Gaussians drawn from all rows with probability
                  proportional to o, with the same correction, appended after the rows
        the Adam moments of every row written (sources, relocated and added rows) are zero
    every iteration, after the Adam step (frozen steps too):
        means += Sigma (z * sigmoid(100 (1 - o - 0.995)) * noise_lr * lr_means),   z ~ N(0, I),
                 Sigma = R diag(s)^2 R^T                            (noise for nearly transparent Gaussians only)
    every iteration, in the loss:
        + opacity_reg * mean(o) + scale_reg * mean(s)

Initial Gaussians: opacity ``init_opacity`` (0.5) and scales ``init_scale`` (0.1) times the nearest-neighbour scale,
as gsplat's MCMC recipe; a point cloud larger than the cap is subsampled to it.

Deliberate differences from gsplat, each for exactness: the correction is computed in float64 (gsplat's CUDA kernel
sums the alternating series in float32, whose cancellation loses digits for large N); relocated rows (not only their
sources) get zero moments, as the paper's code does for its sources and as the rows are new Gaussians. Random
numbers: the draws of each refinement come from NumPy's PCG64 keyed by (seed, refinement counter), the position
noise from Dr.Jit's PCG32 keyed by (seed, iteration) and the row, so a resumed run draws the same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.special import comb

from ..config import MCMCConfig, check_section
from ..conventions import logit
from ..conventions import sigmoid as sigmoid_np
from ..drjit_utils import flat_mean, quaternion_to_matrix, sigmoid
from .adam import GaussianAdam
from .strategy import StepInfo, Strategy

#: Largest number of copies sharing one source in the correction (gsplat's binomial table holds 51 rows: N <= 50).
MAX_RATIO = 50
#: Largest opacity after relocation: 1 - float32 epsilon (gsplat's clamp).
MAX_OPACITY = 1.0 - 2.0 ** -23


def relocation(opacity, scale, ratio) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 9 of the paper: (new opacity (M,), new scale (M, 3)), float64, of a Gaussian of opacity ``opacity`` (M,)
    and scale ``scale`` (M, 3) (activated values) shared by ``ratio`` (M,) copies (clipped to 1..:data:`MAX_RATIO`).

    The double sum over i and k is summed over i in closed form (sum_{i=k+1..N} C(i-1, k) = C(N, k+1)), so the
    denominator is sum_{j=1..N} C(N, j) (-1)^(j-1) o'^j / sqrt(j). The new opacity is not clamped here."""
    o = np.asarray(opacity, np.float64).reshape(-1)
    s = np.asarray(scale, np.float64).reshape(-1, 3)
    n = np.clip(np.asarray(ratio, np.int64).reshape(-1), 1, MAX_RATIO)
    if not (len(o) == len(s) == len(n)):
        raise ValueError(f"relocation: {len(o)} opacities, {len(s)} scales and {len(n)} ratios")
    new_o = 1.0 - np.power(1.0 - o, 1.0 / n)
    if len(o) == 0:
        return new_o, s.copy()
    j = np.arange(1, int(n.max()) + 1, dtype=np.float64)
    terms = comb(n[:, None], j[None, :]) * np.where(j % 2 == 1, 1.0, -1.0) / np.sqrt(j) * new_o[:, None] ** j
    denom = terms.sum(axis=1)          # (terms with j > N are 0: C(N, j) = 0)
    return new_o, s * (o / denom)[:, None]


@dataclass
class MCMCState:
    """The strategy's state: only the counter of refinements that drew random numbers (no per-Gaussian statistics)."""

    draws: int = 0


class MCMCStrategy(Strategy):
    """MCMC densification (see the module docstring). ``seed``: of the relocation draws and the position noise."""

    def __init__(self, cfg: MCMCConfig, seed: int = 0):
        check_section("mcmc", cfg)
        self.cfg = cfg
        self.seed = int(seed)
        self.init_opacity = float(cfg.init_opacity)
        self.init_scale = float(cfg.init_scale)
        self.max_gaussians = int(cfg.cap_max)

    @classmethod
    def from_config(cls, cfg, extent: float, white_background: bool,
                    empty_background: bool = False) -> "MCMCStrategy":
        return cls(cfg.mcmc, seed=cfg.seed + 2)

    # ------------------------------------------------------------------ state
    def initialize_state(self, n: int) -> MCMCState:
        return MCMCState()

    def permute_state(self, state: MCMCState, rows) -> None:
        """(No per-row statistics.)"""

    def export_state(self, state: MCMCState) -> tuple[dict[str, np.ndarray], dict]:
        return {}, {"kind": "mcmc", "seed": self.seed, "draws": state.draws}

    def import_state(self, arrays: dict, meta: dict, n: int) -> MCMCState:
        if arrays or (meta and meta.get("kind") != "mcmc"):
            raise ValueError("the checkpoint was written by another densification strategy")
        state = MCMCState()
        if meta:
            self.seed = int(meta.get("seed", self.seed))
            state.draws = int(meta.get("draws", 0))
        return state

    # ------------------------------------------------------------------ schedule
    def refines_at(self, step: int) -> bool:
        c = self.cfg
        return c.refine_start_iter < step < c.refine_stop_iter and step % c.refine_every == 0

    def updates_state_at(self, step: int) -> bool:
        return False

    def update_state(self, state, out, active=True) -> None:
        pass

    # ------------------------------------------------------------------ every iteration
    def regularization(self, params):
        """``opacity_reg * mean(o) + scale_reg * mean(exp(scales))`` (gsplat's MCMC recipe), or None when both are
        0."""
        c = self.cfg
        terms = []
        if c.opacity_reg:
            terms.append(float(c.opacity_reg) * flat_mean(sigmoid(params["opacities"].array)))
        if c.scale_reg:
            terms.append(float(c.scale_reg) * flat_mean(dr.exp(params["scales"].array)))
        if not terms:
            return None
        return terms[0] if len(terms) == 1 else terms[0] + terms[1]

    def position_noise(self, params: GaussianAdam, step, means_lr) -> "mi.Vector3f":
        """The noise added to the means after the Adam step of iteration ``step`` (see the module docstring)."""
        n = params.n
        o = sigmoid(dr.detach(params["opacities"].array))
        sigma = dr.exp(dr.unravel(mi.Vector3f, dr.detach(params["scales"].array)))
        rot = quaternion_to_matrix(dr.unravel(mi.Vector4f, dr.detach(params["rotations"].array)))
        key = mi.sample_tea_64(mi.UInt32(step), mi.UInt32(self.seed & 0xFFFFFFFF))
        rng = mi.PCG32(size=n, initstate=key, initseq=dr.arange(mi.UInt64, n))
        z = mi.Vector3f(rng.next_float32_normal(), rng.next_float32_normal(), rng.next_float32_normal())
        gate = dr.rcp(1.0 + dr.exp(-100.0 * ((1.0 - o) - 0.995)))
        z *= gate * (mi.Float(means_lr) * float(self.cfg.noise_lr))
        # Sigma z = R diag(sigma^2) R^T z
        return rot @ (sigma * sigma * (rot.T @ z))

    def step_post_update(self, params: GaussianAdam, state, step, means_lr, active=True) -> None:
        """Add the position noise (every iteration; where ``active`` is False the means stay)."""
        if not self.cfg.noise_lr:
            return
        noise = self.position_noise(params, step, means_lr)
        means = dr.unravel(mi.Vector3f, dr.detach(params["means"].array))
        moved = dr.select(active, means + noise, means) if active is not True else means + noise
        params.replace("means", mi.TensorXf(dr.ravel(moved), (params.n, 3)))

    # ------------------------------------------------------------------ refinement
    def step_post_backward(self, params: GaussianAdam, state: MCMCState, step: int, out) -> StepInfo:
        """On the refinement iterations: relocate the dead Gaussians, then add new ones up to the cap (``out`` is not
        read: MCMC keeps no statistics)."""
        return self.refine(params, state, step)

    def refine(self, params: GaussianAdam, state: MCMCState, step: int) -> StepInfo:
        """Relocate the dead Gaussians, then add new ones up to the cap, when ``step`` is a refinement iteration."""
        info = StepInfo(n=params.n)
        if not self.refines_at(step):
            return info
        rng = np.random.default_rng([self.seed, state.draws])
        state.draws += 1
        info.relocated = self._relocate(params, rng)
        info.added = self._add(params, rng)
        info.n = params.n
        info.changed = bool(info.relocated or info.added)
        if info.changed:
            params.clear_grads()
        return info

    def replaces_parameters_at(self, params: GaussianAdam, step: int) -> bool:
        """A dead Gaussian to relocate (beside a live one) or room to grow: else the 3DGS-MCMC reference changes
        nothing and takes the iteration's Adam step."""
        dead = self._opacities(params) <= self.cfg.min_opacity
        return bool(dead.any() and not dead.all()) or self._growth(params.n) > 0

    def _growth(self, n: int) -> int:
        return max(0, min(self.max_gaussians, int((1.0 + self.cfg.growth) * n)) - n)

    def _opacities(self, params: GaussianAdam) -> np.ndarray:
        return sigmoid_np(np.array(params["opacities"].array, np.float64))

    def _corrected(self, params: GaussianAdam, sources: np.ndarray, o: np.ndarray) -> dict:
        """New opacity and scale rows (raw values) of the sources ``sources`` (indices, with repeats) after they are
        shared by their multiplicity + 1 copies."""
        ratio = np.bincount(sources, minlength=len(o))[sources] + 1
        scales = np.exp(np.array(params["scales"].array, np.float64).reshape(-1, 3)[sources])
        new_o, new_s = relocation(o[sources], scales, ratio)
        new_o = np.clip(new_o, max(self.cfg.min_opacity, 1e-30), MAX_OPACITY)   # (logit needs o > 0)
        return {"opacities": logit(new_o).astype(np.float32), "scales": np.log(new_s).astype(np.float32)}

    def _relocate(self, params: GaussianAdam, rng: np.random.Generator) -> int:
        o = self._opacities(params)
        dead = o <= self.cfg.min_opacity
        n_dead = int(dead.sum())
        alive = np.flatnonzero(~dead)
        if n_dead == 0 or len(alive) == 0:
            return 0
        p = o[alive] / o[alive].sum()
        sources = alive[rng.choice(len(alive), size=n_dead, replace=True, p=p)]
        params.set_rows(sources, self._corrected(params, sources, o))
        params.set_rows(np.flatnonzero(dead), params.rows(sources))
        return n_dead

    def _add(self, params: GaussianAdam, rng: np.random.Generator) -> int:
        n = params.n
        n_new = self._growth(n)
        if n_new == 0:
            return 0
        o = self._opacities(params)
        sources = rng.choice(n, size=n_new, replace=True, p=o / o.sum())
        params.set_rows(sources, self._corrected(params, sources, o))
        params.append(params.rows(sources))
        return n_new
