"""The densification ``Strategy`` interface: the hooks a training step calls around its backward pass.

Modelled on gsplat's ``Strategy`` (``gsplat/strategy/base.py``): a strategy holds only its configuration; its running
statistics live in a *state* that the caller creates with :meth:`Strategy.initialize_state`, passes to every hook
and saves with its checkpoints. The state is a dataclass of plain Dr.Jit arrays (and host counters), so a traced or
frozen training step can take it as an input. A strategy changes rows (Gaussians) only through the parameter owner
(:class:`~mi_gaussians.optim.adam.GaussianAdam`), which carries the Adam moments.

One training step (see :mod:`.trainer`)::

    out = render(params.gaussians, camera)
    strategy.step_pre_backward(params, state, step, out)
    dr.backward(loss(out))
    info = strategy.step_post_backward(params, state, step, out)
    if not info.changed:          # rows were rebuilt: the reference's Adam skips that step
        params.step()

To add a strategy: subclass :class:`Strategy`, give it a state dataclass, implement the hooks (and
:meth:`Strategy.export_state` / :meth:`Strategy.import_state` for checkpoints), and select it in the trainer.
:class:`~mi_gaussians.optim.densify.DefaultStrategy` (the paper's adaptive density control) is the reference
implementation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class StepInfo:
    """What a post-backward hook did. ``changed``: rows or values were rebuilt (fresh leaves without gradients), so
    the trainer skips this iteration's Adam step, as the reference's Adam skips its rebuilt parameters."""

    n: int                    # Gaussians afterwards
    changed: bool = False
    densified: bool = False   # a densification (clone / split / prune) ran
    opacity_reset: bool = False
    cloned: int = 0
    split: int = 0            # originals split
    pruned: int = 0           # removed by the prune tests
    reset: int = 0            # opacities lowered by the reset


class Strategy:
    """Base class of densification strategies (see the module docstring)."""

    def initialize_state(self, n: int):
        """A fresh state for a model of ``n`` Gaussians."""
        raise NotImplementedError

    def step_pre_backward(self, params, state, step: int, out) -> None:
        """Called after the render of iteration ``step`` and before ``dr.backward``. Our rasterizer always records
        what densification needs from the backward pass (``RenderOutput.means2d_grad``), so the default does
        nothing; a strategy that must mark something for the backward pass overrides it."""

    def step_post_backward(self, params, state, step: int, out) -> StepInfo:
        """Called after ``dr.backward`` and before the Adam step: update the statistics in ``state`` from ``out``
        (the :class:`~mi_gaussians.raster.rasterize.RenderOutput` of this iteration) and change rows through
        ``params`` when due."""
        raise NotImplementedError

    def export_state(self, state) -> tuple[dict[str, np.ndarray], dict]:
        """(NumPy arrays, JSON-able metadata) of ``state`` for a checkpoint."""
        raise NotImplementedError

    def import_state(self, arrays: dict[str, np.ndarray], meta: dict, n: int):
        """The state :meth:`export_state` saved, for a model of ``n`` Gaussians (a fresh one when ``arrays`` is
        empty); ValueError when it does not fit."""
        raise NotImplementedError
