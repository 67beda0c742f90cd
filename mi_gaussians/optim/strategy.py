"""The densification ``Strategy`` interface: the hooks a training step calls around its backward pass.

Modelled on gsplat's ``Strategy`` (``gsplat/strategy/base.py``): a strategy holds only its configuration; its running
statistics live in a *state* that the caller creates with :meth:`Strategy.initialize_state`, passes to every hook
and saves with its checkpoints. The state is a dataclass of plain Dr.Jit arrays (and host counters), so a traced or
frozen training step can take it as an input. A strategy changes rows (Gaussians) only through the parameter owner
(:class:`~mi_gaussians.optim.adam.GaussianAdam`), which carries the Adam moments.

One training step, as gsplat's loop calls it::

    out = render(params.gaussians, camera)
    strategy.step_pre_backward(params, state, step, out)
    dr.backward(loss(out))
    info = strategy.step_post_backward(params, state, step, out)   # statistics, then refine()
    if not info.changed:          # rows were rebuilt: the reference's Adam skips that step
        params.step()

:meth:`Strategy.step_post_backward` has two parts: the statistics, :meth:`Strategy.update_state` (device arithmetic
only, masked by ``active``, so that a frozen step (:mod:`.train_step`) can record it), then the host part,
:meth:`Strategy.refine`, on the iterations where :meth:`Strategy.refines_at` says rows or values may change. Our
trainer (:mod:`.trainer`) calls the two parts itself: the statistics in the iteration, and the refinement of
iteration ``k`` after that iteration's evaluation, saves and checkpoint, so that what is scored and saved as the model
of iteration ``k`` is never one whose new rows have not had a single optimization step (the reference's ``train.py``
reports and saves before its densification block too)::

    (iteration k) render, backward; if strategy.updates_state_at(k): strategy.update_state(state, out, active=ok)
                  Adam step (skipped when strategy.refines_at(k): the reference's rebuilt parameters have none)
    (host work)   evaluate, save, checkpoint the model of iteration k
    (before k+1)  if strategy.refines_at(k): strategy.refine(params, state, k)

Two more hooks run on every iteration, in both paths, as device work: :meth:`Strategy.regularization` adds a term to
the loss before the backward pass, and :meth:`Strategy.step_post_update` changes values after the Adam step (MCMC's
position noise). A strategy also says how the Gaussians of a run start (:attr:`Strategy.init_opacity`,
:attr:`Strategy.init_scale`) and how many there may be (:attr:`Strategy.max_gaussians`).

To add a strategy: subclass :class:`Strategy`, give it a state dataclass, implement :meth:`Strategy.from_config` and
the hooks (and :meth:`Strategy.export_state` / :meth:`Strategy.import_state` for checkpoints), give it a settings
section in ``config.py`` and its name in ``config.STRATEGIES``, and its class in
:data:`mi_gaussians.optim.strategies.CLASSES` (``--strategy`` then accepts it).
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
    relocated: int = 0        # dead Gaussians moved onto live ones (MCMC)
    added: int = 0            # Gaussians added by sampling live ones (MCMC)

    @property
    def rows_changed(self) -> bool:
        """Whether rows were added, removed or moved (not only values changed, as by an opacity reset)."""
        return bool(self.densified or self.pruned or self.relocated or self.added)


class Strategy:
    """Base class of densification strategies (see the module docstring)."""

    #: Opacity of the initial Gaussians, and the factor on their nearest-neighbour scale (the paper's: 0.1 and 1).
    init_opacity: float = 0.1
    init_scale: float = 1.0
    #: The most Gaussians the strategy allows (None: no bound); a larger initial point cloud is subsampled to it.
    max_gaussians: int | None = None
    #: Whether rows that no view can see (zero opacity, appended after the others) change nothing the strategy's
    #: per-iteration hooks compute for the other rows, so that the trainer may pad the model to a size class for its
    #: frozen steps (:mod:`.train_step`, "Size classes"); such a strategy implements :meth:`pad_state` and
    #: :meth:`trim_state`.
    row_padding: bool = False

    @classmethod
    def from_config(cls, cfg, extent: float, white_background: bool, empty_background: bool = False) -> "Strategy":
        """The strategy of a run: ``cfg`` is its :class:`~mi_gaussians.config.TrainConfig` (the strategy reads its
        own section), ``extent`` the scene extent, ``white_background`` whether it trains on white,
        ``empty_background`` whether it fits an object on an empty background (``densify.empty_background``
        resolved)."""
        raise NotImplementedError

    def initialize_state(self, n: int):
        """A fresh state for a model of ``n`` Gaussians."""
        raise NotImplementedError

    def pad_state(self, state, m: int) -> None:
        """Append ``m`` rows of statistics that no view has touched (``row_padding`` strategies)."""
        raise NotImplementedError(f"{type(self).__name__} does not pad its state")

    def trim_state(self, state, n: int) -> None:
        """Keep the first ``n`` rows of the state (``row_padding`` strategies)."""
        raise NotImplementedError(f"{type(self).__name__} does not pad its state")

    def permute_state(self, state, rows) -> None:
        """Put the per-row statistics of ``state`` in the order ``rows`` (a permutation: new row -> old row, a
        ``mi.UInt32``), as :func:`~.row_order.order_rows` does with the parameters' rows."""
        raise NotImplementedError(f"{type(self).__name__} does not reorder its state")

    def step_pre_backward(self, params, state, step: int | None, out, collect: bool = True) -> None:
        """Called after the render of iteration ``step`` and before ``dr.backward``; a frozen step calls it with
        ``step=None`` while it records (so it must do device work only, the same on every iteration). ``collect``
        says whether this iteration's statistics will be gathered (:meth:`updates_state_at`), so that a request
        only the statistics use can be left out when they are not. Our rasterizer always records what
        densification needs from the backward pass (``RenderOutput.means2d_grad``), so the default does nothing;
        a strategy that must mark something for the backward pass overrides it (e.g. ``out.request_absgrad()``)."""

    def regularization(self, params):
        """A term added to the loss, differentiable in ``params``' tensors (a 1-element ``mi.Float``), or None. Device
        arithmetic only: a frozen step records it."""
        return None

    def step_post_update(self, params, state, step, means_lr, active=True) -> None:
        """Called after the Adam step (or its place) of every iteration, frozen or traced: device work
        only, left undone where the 1-element ``mi.Bool`` ``active`` is False. ``step``: the iteration as a
        1-element ``mi.UInt32``; ``means_lr``: this iteration's position learning rate (1-element ``mi.Float``).
        The default does nothing."""

    def step_post_backward(self, params, state, step: int, out) -> StepInfo:
        """Called after ``dr.backward`` and before the Adam step: update the statistics in ``state`` from ``out``
        (the :class:`~mi_gaussians.raster.rasterize.RenderOutput` of this iteration) when :meth:`updates_state_at`,
        then :meth:`refine` when :meth:`refines_at`."""
        if self.updates_state_at(step):
            self.update_state(state, out)
        return self.refine(params, state, step) if self.refines_at(step) else StepInfo(n=params.n)

    def refine(self, params, state, step: int) -> StepInfo:
        """The host part of iteration ``step`` (:meth:`refines_at`): change rows or values through ``params``
        from the statistics in ``state``. When it does (``info.changed``) every parameter is a fresh leaf without
        gradient. May synchronize."""
        raise NotImplementedError

    def replaces_parameters_at(self, params, step: int) -> bool:
        """Whether :meth:`refine` at its iteration ``step`` will change rows or values, so that the iteration's Adam
        step is left out (the reference's order; ``optim.step_on_refine`` takes it anyway). The default: it will."""
        return True

    def refines_at(self, step: int) -> bool:
        """True when :meth:`refine` may change rows or values at iteration ``step`` (host work)."""
        raise NotImplementedError

    def updates_state_at(self, step: int) -> bool:
        """True when :meth:`update_state` does anything at iteration ``step`` (a frozen step records one variant with
        the update and one without)."""
        return True

    def update_state(self, state, out, active=True) -> None:
        """The statistics part of :meth:`step_post_backward`: device arithmetic only (no readback), left unchanged
        where the 1-element ``mi.Bool`` ``active`` is False (a frozen step records it)."""
        raise NotImplementedError

    def export_state(self, state) -> tuple[dict[str, np.ndarray], dict]:
        """(NumPy arrays, JSON-able metadata) of ``state`` for a checkpoint."""
        raise NotImplementedError

    def import_state(self, arrays: dict[str, np.ndarray], meta: dict, n: int):
        """The state :meth:`export_state` saved, for a model of ``n`` Gaussians (a fresh one when ``arrays`` is
        empty); ValueError when it does not fit."""
        raise NotImplementedError
