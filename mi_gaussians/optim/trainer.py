"""The training loop: view -> render -> L1 + D-SSIM -> dr.backward -> densification strategy -> Adam step.

Outputs (all written atomically into ``out_dir``)::

    config.json                  the resolved TrainConfig (and the dataset path)
    checkpoints/ckpt.npz         the latest checkpoint (parameters, Adam moments and step counts, densification
                                 statistics, random-number-generator states, history): ``--resume`` continues from it
    point_cloud.ply              the final model (3DGS layout); point_cloud_<iter>.ply at cfg.save_iterations
    renders/<view>.exr|.png      test-view renders (EXR linear, PNG display-encoded)
    compare/<view>.png           reference | render | error
    metrics.json                 PSNR / SSIM (LPIPS when available) per test view and mean, Gaussians, time
    curves.png, history.json     loss, test PSNR and number of Gaussians against the iteration

A non-finite loss or parameter stops the run with :class:`TrainingDiverged`; the last good checkpoint stays.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config import TrainConfig
from ..data.dataset import Dataset
from ..drjit_utils import owned_tensor
from ..evaluate import evaluate_views, scores_report, summarize
from ..io_utils import atomic_path
from ..model.gaussians import Gaussians
from ..raster.rasterize import render
from .. import report
from .adam import GaussianAdam
from .densify import DefaultStrategy
from .losses import photometric_loss
from .schedules import expon_lr, sh_degree_at

CHECKPOINT = Path("checkpoints") / "ckpt.npz"


class TrainingDiverged(RuntimeError):
    """The loss or a parameter became NaN/Inf."""


@dataclass
class History:
    iteration: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    gaussians: list = field(default_factory=list)
    seconds: list = field(default_factory=list)     # training time (evaluation excluded) after each iteration
    eval_iteration: list = field(default_factory=list)
    test_psnr: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class ViewSampler:
    """Random training-view order without replacement, refilled when exhausted (the reference's viewpoint stack)."""

    def __init__(self, n: int, seed: int):
        self.n = n
        self.rng = np.random.default_rng(seed)
        self.stack: list[int] = []

    def next(self) -> int:
        if not self.stack:
            self.stack = list(self.rng.permutation(self.n))
        return int(self.stack.pop())

    def state(self) -> dict:
        return {"rng": self.rng.bit_generator.state, "stack": [int(i) for i in self.stack]}

    def restore(self, s: dict) -> None:
        self.rng.bit_generator.state = s["rng"]
        self.stack = list(s["stack"])


def initial_gaussians(ds: Dataset, sh_degree: int) -> Gaussians:
    if ds.points_xyz is None or len(ds.points_xyz) == 0:
        raise ValueError(f"{ds.root}: the dataset has no initial points")
    return Gaussians.from_points(ds.points_xyz, ds.points_rgb, sh_degree=sh_degree)


class Trainer:
    def __init__(self, ds: Dataset, cfg: TrainConfig, out_dir: str | Path, progress: bool = True):
        if not ds.train:
            raise ValueError(f"{ds.root}: no training views")
        self.ds, self.cfg, self.out = ds, cfg, Path(out_dir)
        self.progress = progress
        self.extent = float(ds.extent)
        self.background = tuple(float(b) for b in ds.background)
        self.history = History()
        self.step = 0
        self.elapsed = 0.0        # training seconds (evaluation excluded)
        self.bg_rng = np.random.default_rng(cfg.seed + 1)
        self.sampler = ViewSampler(len(ds.train), cfg.seed)
        # Targets are decoded once and kept as Dr.Jit tensors (copied into Dr.Jit-owned memory). With a random
        # background, RGBA targets are re-composited over the same random colour each iteration (the reference
        # keeps them composited over the fixed one), so we also keep the coverage (1 - alpha).
        self.targets = [owned_tensor(v.load_image()) for v in ds.train]
        self.transparency = None
        if cfg.optim.random_background:
            self.transparency = [owned_tensor(1.0 - v.load_alpha()[..., None]) for v in ds.train]
        self.params = GaussianAdam(initial_gaussians(ds, cfg.optim.sh_degree), cfg.optim, self.extent)
        self.strategy = DefaultStrategy(cfg.densify, self.extent, seed=cfg.seed + 2,
                                        white_background=self.background == (1.0, 1.0, 1.0))
        self.strategy_state = self.strategy.initialize_state(self.params.n)

    @property
    def gaussians(self) -> Gaussians:
        """The model being trained (a view of the optimizer's tensors)."""
        return self.params.gaussians

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self) -> None:
        values = self.gaussians.numpy()
        for k, v in values.items():
            if not np.all(np.isfinite(v)):
                raise TrainingDiverged(f"parameter {k!r} became non-finite at iteration {self.step}; "
                                       f"the last good checkpoint ({self.out / CHECKPOINT}) is kept")
        arrays = {f"param/{k}": v for k, v in values.items()}
        for k, v in self.params.export_moments().items():
            arrays[f"adam/{k}"] = v
        stats, strategy_meta = self.strategy.export_state(self.strategy_state)
        for k, v in stats.items():
            arrays[f"densify/{k}"] = v
        meta = {"step": self.step, "elapsed": self.elapsed, "history": self.history.to_dict(),
                "sampler": self.sampler.state(), "bg_rng": self.bg_rng.bit_generator.state,
                "strategy": strategy_meta, "config": self.cfg.to_dict()}
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
        path = self.out / CHECKPOINT
        with atomic_path(path, suffix=".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)

    def load_checkpoint(self) -> None:
        path = self.out / CHECKPOINT
        if not path.exists():
            raise ValueError(f"{path}: no checkpoint to resume from")
        try:
            with np.load(path) as z:
                data = {k: z[k] for k in z.files}
            meta = json.loads(bytes(data.pop("meta")).decode("utf-8"))
        except Exception as e:
            raise ValueError(f"{path}: unreadable checkpoint ({e})") from None
        def section(prefix):
            return {k.split("/", 1)[1]: v for k, v in data.items() if k.startswith(prefix + "/")}

        try:
            self.params = GaussianAdam(Gaussians.from_numpy(**section("param")), self.cfg.optim, self.extent)
            self.params.import_moments(section("adam"))
            self.strategy_state = self.strategy.import_state(section("densify"), meta["strategy"], self.params.n)
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{path}: checkpoint does not fit this run ({e})") from None
        self.step = int(meta["step"])
        self.elapsed = float(meta["elapsed"])
        self.history = History(**meta["history"])
        self.sampler.restore(meta["sampler"])
        self.bg_rng.bit_generator.state = meta["bg_rng"]

    def target(self, idx: int, bg) -> "mi.TensorXf":
        """Training view ``idx``'s image over background ``bg`` (only RGBA images change with the background)."""
        target = self.targets[idx]
        if self.transparency is not None:
            # image = straight * a + fixed_bg * (1 - a)  ->  straight * a + bg * (1 - a)
            delta = mi.TensorXf(mi.Float([b - f for b, f in zip(bg, self.background)]), (1, 1, 3))
            target = target + self.transparency[idx] * delta
        return target

    # ------------------------------------------------------------------ one iteration
    def _iteration(self, step: int) -> float:
        cfg = self.cfg
        o = cfg.optim
        self.params.set_learning_rate("means", self.extent * expon_lr(
            step, o.position_lr_init, o.position_lr_final, o.position_lr_max_steps,
            delay_steps=o.position_lr_delay_steps, delay_mult=o.position_lr_delay_mult))
        g = self.params.gaussians
        degree = sh_degree_at(step, g.sh_degree, o.sh_increase_interval)
        idx = self.sampler.next()
        view = self.ds.train[idx]
        bg = tuple(self.bg_rng.random(3)) if o.random_background else self.background
        out = render(g, view.camera, background=bg, sh_degree=degree, cfg=cfg.raster)
        self.strategy.step_pre_backward(self.params, self.strategy_state, step, out)
        loss = photometric_loss(out.rgb, self.target(idx, bg), o.lambda_dssim)
        # (a view where nothing is visible gives a loss that does not depend on the parameters)
        dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        value = float(loss[0])
        if not math.isfinite(value):
            raise TrainingDiverged(f"the loss became {value} at iteration {step} (view {view.name}); the last good "
                                   f"checkpoint ({self.out / CHECKPOINT}) is kept")
        info = self.strategy.step_post_backward(self.params, self.strategy_state, step, out)
        if not info.changed:
            # (after a densification step the reference's parameters are new tensors without gradients, so its
            # Adam step skips them: we do the same)
            self.params.step()
        return value

    # ------------------------------------------------------------------ evaluation
    def _test_psnr(self) -> float | None:
        if not self.ds.test:
            return None
        scores, _ = evaluate_views(self.gaussians, self.ds.test, self.background, cfg=self.cfg.raster, with_lpips=False,
                                   color_space=self.ds.color_space)
        return summarize(scores)["psnr"]

    def run(self, resume: bool = False) -> dict:
        from tqdm import tqdm

        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        if resume:
            self.load_checkpoint()
        saved = {"dataset": str(Path(self.ds.root).resolve()), "train": cfg.to_dict()}
        if self.ds.references is not None:
            saved["references"] = str(Path(self.ds.references).resolve())
        report.write_json(self.out / "config.json", saved)
        total = cfg.optim.iterations
        bar = tqdm(total=total, initial=self.step, disable=not self.progress, unit="it", dynamic_ncols=True)
        ema, last_psnr = None, (self.history.test_psnr[-1] if self.history.test_psnr else None)
        try:
            while self.step < total:
                step = self.step + 1
                t0 = time.perf_counter()
                loss = self._iteration(step)
                self.elapsed += time.perf_counter() - t0
                self.step = step
                ema = loss if ema is None else 0.4 * loss + 0.6 * ema
                self.history.iteration.append(step)
                self.history.loss.append(loss)
                self.history.gaussians.append(self.params.n)
                self.history.seconds.append(round(self.elapsed, 4))
                if cfg.eval_every and step % cfg.eval_every == 0 or step == total:
                    last_psnr = self._test_psnr()
                    if last_psnr is not None:
                        self.history.eval_iteration.append(step)
                        self.history.test_psnr.append(last_psnr)
                if step in cfg.save_iterations and step != total:
                    self.gaussians.save_ply(self.out / f"point_cloud_{step}.ply")
                if step % cfg.checkpoint_every == 0 or step == total:
                    self.save_checkpoint()
                bar.update(1)
                if step % 10 == 0 or step == total:
                    post = {"loss": f"{ema:.4f}", "N": f"{self.params.n:,}"}
                    if last_psnr is not None:
                        post["PSNR"] = f"{last_psnr:.2f}"
                    bar.set_postfix(post)
        finally:
            bar.close()
        return self.finish()

    def finish(self) -> dict:
        """Final outputs: PLY, test renders and comparisons, metrics.json, curves."""
        g = self.gaussians
        g.save_ply(self.out / "point_cloud.ply")
        views = self.ds.test if self.ds.test else self.ds.train[:1]
        scores, note = evaluate_views(g, views, self.background, cfg=self.cfg.raster, keep_images=True,
                                      color_space=self.ds.color_space)
        report.write_view_outputs(self.out, scores, self.ds.color_space)
        metrics = {
            "split": "test" if self.ds.test else "train (no test views)",
            **scores_report(scores, note),
            "gaussians": g.n,
            "iterations": self.step,
            "training_seconds": round(self.elapsed, 3),
            "iterations_per_second": round(self.step / self.elapsed, 3) if self.elapsed > 0 else None,
        }
        report.write_json(self.out / "metrics.json", metrics)
        report.write_json(self.out / "history.json", self.history.to_dict())
        report.plot_curves(self.out / "curves.png", self.history.to_dict())
        return metrics
