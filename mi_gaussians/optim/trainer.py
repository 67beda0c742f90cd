"""The training loop: view -> render -> L1 + D-SSIM -> dr.backward -> statistics -> Adam step -> (evaluation, saves)
-> the densification strategy's refinement.

Outputs: :mod:`.outputs` (and ``docs/reference/run-folder.md``); checkpoints: :mod:`.checkpoint`.

Iterations are frozen (:mod:`.train_step`: recorded once with ``dr.freeze``, replayed, nothing read back) and queued;
:meth:`Trainer._resolve` reads their losses and flags every :data:`SYNC_EVERY` iterations and before evaluations,
checkpoints and refinements. The first iteration and the strategy's refinement iterations run traced
(:meth:`Trainer._iteration`); ``TrainConfig.freeze = False`` traces every iteration.

Iteration ``k``'s refinement runs after its evaluation, saves and checkpoint (:meth:`Trainer._refine`), as in the
reference's ``train.py``: the model scored and saved as iteration ``k`` never holds rows without an optimization step.

A non-finite loss, or any trained quantity becoming non-finite (:mod:`.guard`, checked at every synchronization and
before every checkpoint), stops the run with :class:`TrainingDiverged`; the last good checkpoint stays.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import TrainConfig
from ..data.dataset import Dataset
from ..drjit_utils import exact_float_math
from ..evaluate import evaluate_views, summarize
from ..model.gaussians import Gaussians
from ..raster.blend import LaneLayout, balanced_layout, lane_layout
from ..raster.rasterize import render
from .. import run_folder
from . import checkpoint, guard
from .adam import GaussianAdam
from .compensation import make_compensation
from .guard import TrainingDiverged  # noqa: F401  (raised here; importers take it from this module too)
from .pose import PoseDeltas, pivot_depths
from .row_order import order_rows
from .loop_state import History, LoopStats, Pending, TrainingStopped, ViewSampler  # noqa: F401  (TrainingStopped:
# raised here, and importers take it from this module)
from .strategies import empty_background, initial_gaussians, make_strategy
from .targets import TrainingViews
from .schedules import depth_weight, position_lr, sh_degree_at
from .train_step import (StepInputs, TrainStep, capacity_for, composite_target, pad_rows, row_class, training_loss,
                         trim_rows)

CHECKPOINT = Path(run_folder.CHECKPOINT)

# Frozen iterations queued between two reads of their losses and flags (progress bar, history, overflow, NaN). More
# keeps the device busier; fewer wastes fewer iterations when one overflows its instance capacity and is replayed.
SYNC_EVERY = 25


class Trainer:
    def __init__(self, ds: Dataset, cfg: TrainConfig, out_dir: str | Path, progress: bool = True,
                 given_cameras: list | None = None):
        """``given_cameras``: the training cameras as the dataset gives them, where ``ds`` holds perturbed ones
        (``data.pose_noise``): the run reports its cameras' errors against them."""
        if not ds.train:
            raise ValueError(f"{ds.root}: no training views")
        self.ds, self.cfg, self.out = ds, cfg, Path(out_dir)
        self.given_cameras = given_cameras or [v.camera for v in ds.train]
        self.progress = progress
        self.extent = float(ds.scene_extent(cfg.data.extent))
        self.background = tuple(float(b) for b in ds.background)
        self.history = History()
        self.step = 0
        self.resumed_from: int | None = None    # the checkpoint's iteration, when run(resume=True) continued one
        self.run_id: str | None = None          # the run's identity (config.json and every checkpoint: run())
        self.stop_signal: int | None = None     # set (e.g. by a signal handler) to stop after the iteration running
        self.elapsed = 0.0        # training seconds (evaluation excluded)
        self.bg_rng = np.random.default_rng(cfg.seed + 1)
        self.sampler = ViewSampler(len(ds.train), cfg.seed)
        # what each step takes of each training view: its camera and target, at the coarse-to-fine schedule's scale
        self.views = TrainingViews(ds, cfg)
        #: whether the run fits an object on an empty background (densify.empty_background; optim/densify.py)
        self.empty_background = empty_background(cfg.densify.empty_background, self.views.transparent)
        self.strategy = make_strategy(cfg, self.extent, white_background=self.background == (1.0, 1.0, 1.0),
                                      train_cameras=[v.camera for v in ds.train],
                                      empty_background=self.empty_background, training_views=self.views,
                                      background=self.background)
        self.params = GaussianAdam(initial_gaussians(ds, cfg.optim.sh_degree, self.strategy, seed=cfg.seed + 3),
                                   cfg.optim, self.extent)
        self.strategy_state = self.strategy.initialize_state(self.params.n)
        self._sort_rows()
        self.exposure = make_compensation(cfg.optim, len(ds.train))
        self.poses = None
        if cfg.optim.pose_opt:
            pivots = None
            if cfg.optim.pose_opt_pivot == "depth":    # (the scene's points as the run starts: its initial points)
                from ..data.pose_noise import reprojection_points
                pivots = pivot_depths([v.camera for v in ds.train], reprojection_points(ds.points_xyz), ds.center)
            # (translations in units of the cameras' spread, as gsplat's, which normalises the rig: not data.extent)
            self.poses = PoseDeltas(len(ds.train), cfg.optim, float(ds.extent), pivots)
        # the frozen training step (see train_step.py) and the state of the loop around it
        self.train_step = TrainStep(self.strategy, cfg.raster, cfg.optim.lambda_dssim, self.background,
                                    freeze=cfg.freeze, ssim_padding=cfg.optim.ssim_padding,
                                    random_background=cfg.optim.random_background,
                                    alpha_weight=cfg.optim.alpha_weight)
        self.capacity: int | None = None   # tile-instance capacity of frozen steps (set by the first traced one)
        self._needed = 0                   # the instances it was made for
        self.layout = None                 # the blend's lane layout (None: the backend's; see _choose_layout)
        self._layout_due = True            # (chosen at the first iteration and at each refinement)
        self._shares: list[float] = []     # each iteration's heaviest tile's share of its blended instances since
                                           # the last choice of layout
        self._radii = None                 # the footprint radii (mi.Int32, 0: not visible) of the traced
                                           # iteration that chooses the layout
        self._refine_at: int | None = None  # an iteration whose refinement is still to run (see _refine)
        self.loop = LoopStats()            # time split, recordings, overflows, syncs (a refinement's own not counted)
        self._peak = 0                     # most instances a committed frozen step needed since the last traced one
        self._pending: list[Pending] = []
        self._valid = None                 # the last queued step's ok flag (chained into the next)
        self._finite_at = 0                 # the last iteration whose trained quantities were checked finite
        # while frozen steps run on the model padded to its size class (train_step.py, "Size classes"): its own rows
        self._rows: int | None = None
        self._bar, self._ema, self._last_psnr = None, None, None
        self._t0 = time.perf_counter()

    @property
    def gaussians(self) -> Gaussians:
        """The model being trained (a view of the optimizer's tensors, without the frozen steps' padding)."""
        self.trim()
        return self.params.gaussians

    @property
    def n_gaussians(self) -> int:
        """The number of Gaussians of the model (``params.n`` counts the padding while frozen steps run)."""
        return self.params.n if self._rows is None else self._rows

    def trim(self) -> None:
        """Drop the inert rows the frozen steps run with (train_step.py, "Size classes"), so that ``params`` and
        ``strategy_state`` hold the model's own rows; every host-side reader and writer of the rows calls it (the next
        frozen step pads again)."""
        if self._rows is not None:
            trim_rows(self.params, self.strategy_state, self.strategy, self._rows)
            self._rows = None

    def _pad(self) -> None:
        """Pad the model to its size class for the frozen steps (when the strategy allows it and ``row_classes``)."""
        if self._rows is None and self.strategy.row_padding and self.cfg.row_classes > 0:
            n = self.params.n
            pad_rows(self.params, self.strategy_state, self.strategy, self._class_rows())
            self._rows = n

    # ------------------------------------------------------------------ checkpoints
    def check_finite(self) -> None:
        """:class:`TrainingDiverged` unless every trained quantity is finite (:mod:`.guard`); reads one flag per
        parameter group (a synchronization; inert padding rows are finite, so no trim is needed)."""
        guard.check(guard.flags(self.params, self.poses, self.exposure), self.cfg.optim, self._finite_at, self.step,
                    self.out / CHECKPOINT)
        self._finite_at = self.step

    def save_checkpoint(self) -> None:
        self.check_finite()
        values = self.gaussians.numpy()         # (without the padding: trimmed)
        stats, strategy_meta = self.strategy.export_state(self.strategy_state)
        sections = {"param": values, "adam": self.params.export_moments(), "densify": stats}
        if self.exposure is not None:
            sections["exposure"] = self.exposure.export()
        if self.poses is not None:
            sections["pose"] = self.poses.export()
        self.loop.close(self.elapsed)
        meta = {"step": self.step, "run_id": self.run_id, "refine_pending": self._refine_at, "elapsed": self.elapsed,
                "history": self.history.to_dict(), "loop": self.loop.to_dict(),
                "sampler": self.sampler.state(), "bg_rng": self.bg_rng.bit_generator.state,
                "strategy": strategy_meta, "config": self.cfg.to_dict(),
                "layout": None if self.layout is None else dataclasses.asdict(self.layout)}
        checkpoint.write(self.out / CHECKPOINT, sections, meta)

    def load_checkpoint(self) -> None:
        path = self.out / CHECKPOINT
        sections, meta = checkpoint.read(path)
        checkpoint.check_identity(path, meta, self.run_id, self.cfg, self.out / run_folder.CONFIG)
        self.run_id = self.run_id or meta.get("run_id")
        try:
            self._rows = None
            self.params = GaussianAdam(Gaussians.from_numpy(**sections.get("param", {})), self.cfg.optim, self.extent)
            self.params.import_moments(sections.get("adam", {}))
            self.strategy_state = self.strategy.import_state(sections.get("densify", {}), meta["strategy"],
                                                             self.params.n)
            if self.exposure is not None:
                self.exposure.restore(sections.get("exposure", {}))
            if self.poses is not None:
                self.poses.restore(sections.get("pose", {}))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{path}: checkpoint does not fit this run ({e})") from None
        self.step = self._finite_at = int(meta["step"])
        # (a checkpoint of iteration k written before k's refinement; older checkpoints were written after it)
        pending = meta.get("refine_pending")
        self._refine_at = None if pending is None else int(pending)
        if self.step > self.cfg.optim.iterations:
            raise ValueError(f"{path}: the run is already at iteration {self.step}, past the "
                             f"{self.cfg.optim.iterations} iterations asked for")
        self.elapsed = float(meta["elapsed"])
        self.history = History(**meta["history"])
        self.loop = LoopStats.from_dict(meta.get("loop"))
        self.sampler.restore(meta["sampler"])
        self.bg_rng.bit_generator.state = meta["bg_rng"]
        if meta.get("layout") is not None:      # (the blend's layout as chosen, until the next choice)
            self.layout, self._layout_due = LaneLayout(**meta["layout"]), False

    def target(self, idx: int, bg) -> "mi.TensorXf":
        """Training view ``idx``'s image over background ``bg`` (only RGBA images change with the background), at the
        current coarse-to-fine scale."""
        transparency = self.views.transparency_of(idx) if self.cfg.optim.random_background else None
        return composite_target(self.views.target(idx), transparency, bg, self.background)

    # ------------------------------------------------------------------ one iteration
    def _draw(self) -> tuple[int, tuple]:
        """The training view and the background colour of the next iteration (advances both random streams)."""
        idx = self.sampler.next()
        bg = tuple(self.bg_rng.random(3)) if self.cfg.optim.random_background else self.background
        return idx, bg

    def _iteration(self, step: int, keep_radii: bool = False) -> tuple[float, int, int]:
        """One traced iteration (synchronizes: reads the loss and the instance count back). On a refinement iteration
        it gathers the statistics and leaves the refinement pending (:meth:`_refine`, at the start of the next
        iteration); ``keep_radii``: its Gaussians' footprint radii are kept for the choice of layout after it. Returns
        (loss, tile instances, instances blended)."""
        cfg = self.cfg
        o = cfg.optim
        self.trim()
        # (a Dr.Jit value, as in the frozen step, so both paths leave the optimizer state of the same type)
        self.params.set_learning_rate("means", dr.opaque(mi.Float, position_lr(step, o, self.extent)))
        g = self.params.gaussians
        degree = sh_degree_at(step, g.sh_degree, o.sh_increase_interval)
        idx, bg = self._draw()
        views = self.views
        views.set_scale(views.scale_at(step))
        camera = views.camera(idx) if self.poses is None else self.poses.view(views.view(idx), idx)
        depth = views.depth_of(idx)
        out = render(g, camera, background=bg, sh_degree=degree, cfg=cfg.raster, layout=self.layout,
                     depth=depth is not None)
        self.strategy.step_pre_backward(self.params, self.strategy_state, step, out,
                                        collect=self.strategy.updates_state_at(step))
        loss = training_loss(out, self.target(idx, bg), o.lambda_dssim, self.strategy, self.params, depth,
                             None if depth is None else dr.opaque(mi.Float, depth_weight(step, o)), self.exposure,
                             dr.opaque(mi.UInt32, idx), o.ssim_padding, views.transparency_of(idx), o.alpha_weight)
        # (a view where nothing is visible gives a loss that does not depend on the parameters)
        dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        value = float(loss[0])
        self.loop.syncs += 2     # (this read, and the binning's read of its instance count)
        if not math.isfinite(value):
            raise self._diverged(value, step, idx)
        if self.strategy.updates_state_at(step):
            self.strategy.update_state(self.strategy_state, out)
        refines = self.strategy.refines_at(step)
        if refines and not o.step_on_refine and self.strategy.replaces_parameters_at(self.params, step):
            # (the reference's Adam skips it: its rebuilt parameters have no gradient; gsplat's steps: step_on_refine)
            self.params.clear_grads()
        else:
            self.params.step()
        self.strategy.step_post_update(self.params, self.strategy_state, dr.opaque(mi.UInt32, step),
                                       dr.opaque(mi.Float, position_lr(step, o, self.extent)))
        if self.exposure is not None:          # (every iteration, as the reference's exposure optimizer)
            self.exposure.set_learning_rate(dr.opaque(mi.Float, self.exposure.learning_rate(step)))
            self.exposure.step()
        if self.poses is not None:             # (every iteration, as gsplat's pose optimizer)
            self.poses.set_learning_rate(dr.opaque(mi.Float, self.poses.learning_rate(step)))
            self.poses.step(idx)
        if refines:
            self._refine_at = step
        blended = int(out.n_blended[0]) if dr.is_array_v(out.n_blended) else 0
        self._note_load(blended, out.max_tile)
        if keep_radii:
            self._radii = out.radii
        return value, int(out.n_instances), blended

    def _refine(self) -> None:
        """The strategy's refinement of iteration ``self._refine_at`` (densification, pruning, opacity reset), after
        that iteration's evaluation, saves and checkpoint; the frozen steps' instance capacity follows the new number
        of Gaussians."""
        step, self._refine_at = self._refine_at, None
        self.trim()
        n_before = self.params.n
        if self.strategy.refine(self.params, self.strategy_state, step).rows_changed:
            self._sort_rows()
        if self.capacity is not None and self.params.n != n_before:
            self._set_capacity_after_traced(round(self._needed * self.params.n / n_before))

    def _sort_rows(self) -> None:
        """The model's rows, their moments and the strategy's statistics in space order (``optim.row_order``
        'spatial'; :mod:`.row_order`), at the start and after each refinement that changed rows."""
        if self.cfg.optim.row_order == "spatial":
            order_rows(self.params, self.strategy, self.strategy_state)

    def _diverged(self, loss: float, step: int, view: int) -> TrainingDiverged:
        return TrainingDiverged(f"the loss became {loss} at iteration {step} (view {self.ds.train[view].name}); the "
                                f"last good checkpoint ({self.out / CHECKPOINT}) is kept")

    def _traced_at(self, step: int) -> bool:
        """Whether iteration ``step`` runs traced: always without freezing; else the first one (it measures the
        instance count) and those where the strategy refines (host work that may synchronize anyway)."""
        return not self.cfg.freeze or self.capacity is None or self.strategy.refines_at(step)

    def _set_capacity_after_traced(self, instances: int) -> None:
        """The frozen steps' instance capacity after a traced iteration: room for 1.15 times what it needed, or the
        peak of the frozen steps before it (a refinement then scales it by the change in the number of Gaussians),
        scaled from the model's rows to its size class's; the capacity in use stays while it holds 1.1 to 1.5 times
        that. (A view's instances differ from the mean by about 5 % on the 7k models of mi_objects/colmap and the
        400x400 table; the capacity-wide kernels are a tenth of the step, and with room for 1.3 times, kept up to
        2 times, on the coarser ladder, the frozen steps took 1.03-1.05x the time.)"""
        self._needed = max(instances, self._peak, 1)
        # Sized for the model's whole size class (the instances grow with the Gaussians), and kept while it leaves
        # 10 % headroom and is under 1.5 times that: each new capacity, like each new class, is a new recording.
        need = self._needed * self._class_rows() / self.n_gaussians
        if self.capacity is None or not 1.1 * need <= self.capacity <= 1.5 * need:
            self.capacity = capacity_for(1.15 * need)
        self._peak = 0

    def _note_load(self, blended: int, max_tile) -> None:
        """Keep an iteration's heaviest tile's share of its ``blended`` instances (``max_tile``: the device count) for
        the next :meth:`_choose_layout` (nothing when it blended none)."""
        if blended:
            self._shares.append(int(max_tile[0]) / blended)

    def _choose_layout(self) -> None:
        """The blend's lane layout from the first iteration and from each refinement iteration on (``raster.lanes``
        'balanced'; the frozen loop's traced iterations, so that a new layout, a new recording of the frozen step, comes
        at most every 100 iterations while densifying): the one :func:`~mi_gaussians.raster.blend.balanced_layout`
        gives for the mean share of the heaviest tile over the iterations since the last choice and, on the CPU, the
        mean footprint radius of the Gaussians the iteration just traced shows. The traced loop chooses at the same
        iterations from the same renders. A new tile grid (the CPU's layouts) drops the frozen steps' capacity and
        peak, which the old grid's tiles counted: the next iteration is traced and measures them anew."""
        if self.cfg.raster.lanes == "balanced" and self._shares:
            share = sum(self._shares) / len(self._shares)
            cuda = dr.backend_v(mi.Float) == dr.JitBackend.CUDA
            radius = None
            if not cuda and self._radii is not None:
                visible = int(dr.count(self._radii > 0)[0])
                radius = float(dr.sum(mi.Float(self._radii))[0]) / visible if visible else None
            before = (self.layout or lane_layout()).tile
            self.layout = balanced_layout(share, cuda=cuda, radius=radius)
            if self.layout.tile != before:
                self.capacity, self._peak = None, 0
                self.loop.regrids += 1
        self._shares, self._radii, self._layout_due = [], None, False

    def _class_rows(self) -> int:
        """The rows of the size class of the model (:func:`.train_step.row_class`; its own rows when not padded)."""
        n = self.n_gaussians
        return row_class(n, self.cfg.row_classes) if self.strategy.row_padding else n

    def _dispatch(self, step: int) -> None:
        """Queue frozen iteration ``step`` (no synchronization); its results are read by :meth:`_resolve`."""
        cfg = self.cfg
        host = (self.sampler.state(), self.bg_rng.bit_generator.state)
        idx, bg = self._draw()
        views = self.views
        views.set_scale(views.scale_at(step))
        depth = views.depth_of(idx)
        inputs = StepInputs(target=views.target(idx), transparency=views.transparency_of(idx), view=views.view(idx),
                            background=tuple(dr.opaque(mi.Float, b) for b in bg),
                            means_lr=dr.opaque(mi.Float, position_lr(step, cfg.optim, self.extent)),
                            step=dr.opaque(mi.UInt32, step),
                            depth_target=depth,
                            depth_weight=None if depth is None else dr.opaque(mi.Float, depth_weight(step, cfg.optim)),
                            view_index=None if self.exposure is None and self.poses is None
                            else dr.opaque(mi.UInt32, idx),
                            exposure_lr=None if self.exposure is None
                            else dr.opaque(mi.Float, self.exposure.learning_rate(step)),
                            pose_lr=None if self.poses is None
                            else dr.opaque(mi.Float, self.poses.learning_rate(step)))
        degree = sh_degree_at(step, self.params.gaussians.sh_degree, cfg.optim.sh_increase_interval)
        if self._valid is None:
            self._valid = dr.opaque(mi.Bool, True)
        self._pad()
        loss, ok, instances, blended, max_tile = self.train_step(
            self.params, self.strategy_state, inputs, self._valid, degree, self.strategy.updates_state_at(step),
            self.capacity, self.exposure, self.poses, self.layout)
        self._valid = ok
        self._pending.append(Pending(step, idx, host, loss, ok, instances, blended, max_tile))
        self.step = step

    def _resolve(self) -> bool:
        """Read the queued frozen iterations' losses and flags (one synchronization) and commit them. On an instance
        overflow: enlarge the capacity and rewind to the failed iteration (the model is as before it, every later
        step having been masked) and return False. On a non-finite loss: raise :class:`TrainingDiverged`."""
        pending, self._pending = self._pending, []
        if not pending:
            return True
        with self.loop.timed("waiting"):
            dr.sync_thread()
        self.loop.syncs += 1
        for i, p in enumerate(pending):
            ok, loss, instances = bool(p.ok[0]), float(p.loss[0]), int(p.instances[0])
            if not ok:
                self._valid = None
                if instances > self.capacity:
                    self.capacity = capacity_for(1.25 * instances)
                    self.loop.overflows += 1
                    self.loop.replayed += len(pending) - i
                    self.sampler.restore(p.host[0])
                    self.bg_rng.bit_generator.state = p.host[1]
                    self.step = p.step - 1
                    return False
                raise self._diverged(loss, p.step, p.view)
            self._peak = max(self._peak, instances)
            blended = int(p.blended[0])
            self._note_load(blended, p.max_tile)
            self._commit(p.step, loss, blended)
        self.check_finite()
        return True

    def _commit(self, step: int, loss: float, blended: int) -> None:
        """Record a finished iteration (history, progress bar); ``blended``: its (Gaussian, tile) pairs blended."""
        self._ema = loss if self._ema is None else 0.4 * loss + 0.6 * self._ema
        self.history.iteration.append(step)
        self.history.loss.append(loss)
        self.history.gaussians.append(self.n_gaussians)
        self.history.instances.append(blended)
        label = (self.layout or lane_layout()).label
        self.loop.lanes[label] = self.loop.lanes.get(label, 0) + 1
        self.history.seconds.append(round(self.elapsed + time.perf_counter() - self._t0, 4))
        if self._bar is not None:
            self._bar.update(1)
            if step % 10 == 0 or step == self.cfg.optim.iterations:
                self._show_progress(refresh=False)

    def _show_progress(self, refresh: bool = True) -> None:
        """The progress bar's loss, number of Gaussians and latest test PSNR."""
        post = {"loss": f"{self._ema:.4f}", "N": f"{self.n_gaussians:,}"}
        if self._last_psnr is not None:
            post["PSNR"] = f"{self._last_psnr:.2f}"
        self._bar.set_postfix(post, refresh=refresh)

    def _host_work_at(self, step: int) -> bool:
        cfg = self.cfg
        return (bool(cfg.eval_every) and step % cfg.eval_every == 0 or step == cfg.optim.iterations
                or step in cfg.save_iterations or step % cfg.checkpoint_every == 0)

    def advance(self) -> None:
        """Run the pending refinement of the iteration before (if any), then the next iteration (traced or frozen);
        frozen ones are committed every :data:`SYNC_EVERY` iterations and before any host work. Afterwards
        ``self.step`` is the last iteration run or queued (a rewind after an instance overflow moves it back)."""
        step = self.step + 1
        self._t0 = time.perf_counter()
        _, loaded, built = dr.detail.launch_stats()
        try:
            with exact_float_math():             # (the frozen and traced iterations trace the same arithmetic)
                self._advance(step)
        finally:
            self.elapsed += time.perf_counter() - self._t0
            self._t0 = time.perf_counter()
            _, loaded_after, built_after = dr.detail.launch_stats()
            self.loop.compiles += built_after - built
            self.loop.cache_loads += loaded_after - loaded

    def _advance(self, step: int) -> None:
        """The body of :meth:`advance` (iteration ``step``)."""
        if self._refine_at is not None:      # (a traced iteration before it: nothing is queued)
            with self.loop.timed("refinement"):
                self._refine()
            self.loop.refinements += 1
        if self._traced_at(step):
            if not self._resolve():
                return
            choose = self._layout_due or self.strategy.refines_at(step)     # (the frozen loop's traced iterations)
            with self.loop.timed("traced"):
                loss, instances, blended = self._iteration(step, keep_radii=choose)
            self.loop.traced += 1
            self.step = step
            self._commit(step, loss, blended)
            if self.cfg.freeze:
                self._set_capacity_after_traced(instances)
            if choose:
                self._choose_layout()
        else:
            recordings = self.train_step.recordings
            with self.loop.timed("frozen") as part:
                self._dispatch(step)
                new = self.train_step.recordings - recordings
                part[0] = "recording" if new else "frozen"
            self.loop.recordings += new
            if self._host_work_at(step) or len(self._pending) >= SYNC_EVERY:
                self._resolve()

    # ------------------------------------------------------------------ evaluation
    def _test_psnr(self) -> float | None:
        if not self.ds.test:
            return None
        scores, _ = evaluate_views(self.gaussians, self.ds.test, self.background, cfg=self.cfg.raster, with_lpips=False,
                                   color_space=self.ds.color_space)
        return summarize(scores)["psnr"]

    def run(self, resume: bool = False, fingerprint: str | None = None, monitor=None,
            run_id: str | None = None) -> dict:
        """Train to ``cfg.optim.iterations`` (from the checkpoint with ``resume``) and write the outputs;
        ``fingerprint``: of the dataset's content, for the run's record; ``monitor``: called with the trainer
        after every iteration (e.g. a viewer; it may read the model, and must not change it), outside the
        training time; ``run_id``: the identity config.json records for the run being resumed (a checkpoint of
        another run is refused: :func:`.checkpoint.check_identity`), none for a new run (one is made)."""
        import uuid

        from tqdm import tqdm

        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        self.run_id = run_id
        if resume:
            self.load_checkpoint()
            self.resumed_from = self.step
        self.run_id = self.run_id or uuid.uuid4().hex
        refs = None if self.ds.references is None else str(Path(self.ds.references).resolve())
        run_folder.RunRecord(str(Path(self.ds.root).resolve()), cfg, fingerprint, refs, self.run_id).write(self.out)
        total = cfg.optim.iterations
        self._bar = tqdm(total=total, initial=self.step, disable=not self.progress, unit="it", dynamic_ncols=True)
        self._ema = None
        self._last_psnr = self.history.test_psnr[-1] if self.history.test_psnr else None
        done = self.step                         # the last iteration whose evaluation / saving / checkpoint ran
        try:
            while self.step < total or self._pending:
                self._stop_if_asked()
                if self.step < total:
                    self.advance()
                else:
                    self._drain()
                if monitor is not None:
                    monitor(self)
                step = self.step
                if self._pending or step <= done or not self._host_work_at(step):
                    continue
                done = step                      # (a rewind never goes back past it: it was synchronized)
                if cfg.eval_every and step % cfg.eval_every == 0 or step == total:
                    with self.loop.timed("evaluation"):
                        self._last_psnr = self._test_psnr()
                    if self._last_psnr is not None:
                        self.history.eval_iteration.append(step)
                        self.history.test_psnr.append(self._last_psnr)
                        if self._ema is not None:        # (the bar ends on the last evaluation)
                            self._show_progress()
                with self.loop.timed("saving"):
                    if step in cfg.save_iterations and step != total:
                        self.gaussians.save_ply(self.out / run_folder.saved_model(step))
                    if step % cfg.checkpoint_every == 0 or step == total:
                        self.save_checkpoint()
        finally:
            self._bar.close()
            self._bar = None
        return self.finish()

    def _drain(self) -> None:
        """Commit every queued iteration (training time; an overflow rewinds and empties the queue)."""
        t0 = time.perf_counter()
        while self._pending:
            self._resolve()
        self.elapsed += time.perf_counter() - t0

    def _stop_if_asked(self) -> None:
        """When a stop was asked for (:attr:`stop_signal`): commit the queued iterations, write a checkpoint and raise
        :class:`TrainingStopped` (while the final outputs are written: at the last iteration; a resume writes them)."""
        if self.stop_signal is not None:
            self._drain()
            self.save_checkpoint()
            raise TrainingStopped(self.stop_signal, self.step)

    def finish(self) -> dict:
        """Final outputs (:func:`.outputs.write_outputs`): PLY, test renders and comparisons, metrics.json, curves.
        A stop asked for while they are written (before metrics.json, the run's last word) stops the run at its last
        iteration."""
        from .outputs import write_outputs

        return write_outputs(self)
