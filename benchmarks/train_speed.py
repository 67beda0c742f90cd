"""Training-loop throughput: the frozen training step (``dr.freeze``, the default) against the traced loop
(``--set freeze=false``, every iteration traced in Python and synchronized), in the same run.

    python benchmarks/train_speed.py                                  # synthetic 200x200/50k and 800x800/300k
    python benchmarks/train_speed.py --cases 200:50000 --iterations 40
    python benchmarks/train_speed.py --cases mi_objects_colmap --iterations 100 --rounds 5   # a real run's start
    python benchmarks/train_speed.py --variant cuda_ad_rgb --busy 1000 --profile

Per case and loop it prints:
- iterations/s: wall clock over ``--rounds`` passes of ``--iterations`` iterations (after a warm-up that compiles
  and records), the two loops taking turns pass by pass, so that both see the same stretch of the schedule and the
  same drift of the machine's speed;
- host ms/it: time the host spends tracing, recording or replaying, and launching: each iteration run once more with
  ``JitFlag.LaunchBlocking`` (each kernel finishes before the host goes on), its wall time minus its kernels' own
  time; the median over the iterations (a 2-core VM stalls now and then for milliseconds, which a mean over a few
  dozen iterations would count as host time), and the mean beside it (it also carries the queued iterations' read
  every ``trainer.SYNC_EVERY`` iterations);
- kernel ms/it and kernels/it: ``dr.kernel_history()`` over the measured iterations (every entry: compiled kernels,
  sorts, reductions, memsets, copies);
- syncs/it: times the training loop waited for the device to read values back (a traced iteration: the binning's
  instance count and the loss; frozen: one read of the queued iterations' losses and flags every
  ``trainer.SYNC_EVERY`` iterations and at evaluations, checkpoints and densification steps; the reads inside a
  densification step are not counted);
- the ratio of iterations/s, frozen over traced;
- with ``--busy K`` on a CUDA variant: each loop runs K more iterations while NVML's GPU utilization (what
  ``nvidia-smi dmon`` prints as ``sm`` %: the share of time a kernel was running) is polled every 20 ms, and the mean
  of the samples taken during the run (after its first 0.3 s) is printed as "GPU busy";
- with ``--profile``: where the frozen step's device time goes (``kernel_profile.py``: launches and ms per iteration
  by kind, the longest compiled kernels).

Synthetic cases ``RES:N`` train N Gaussians (``benchmarks/render.py``'s scene, same seed, initialized from noisy
positions) against 8 renders of that scene at RES x RES, without densification (a fixed model size). A dataset case
trains the default schedule from its first iteration (densification included), as ``benchmarks/train.py`` does;
``mi_objects_colmap`` is 200x200 with 2,274 SfM points (``../shared/data``, skipped when absent).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


class _MemoryLoader:
    """A view's image held in memory (the synthetic cases have no files)."""

    def __init__(self, img):
        self.img = img

    def load(self, path):
        return self.img, None


def synthetic_dataset(res: int, n: int):
    import mitsuba as mi  # noqa: F401  (the variant is set)

    from mi_gaussians.data.camera import Camera
    from mi_gaussians.data.dataset import Dataset, View
    from mi_gaussians.model.gaussians import Gaussians
    from mi_gaussians.raster.rasterize import render
    from render import make_scene

    scene = make_scene(n)
    g = Gaussians.from_numpy(**scene)
    views = []
    for i in range(8):
        a = (i - 3.5) * 0.03
        w2c = np.eye(4)
        w2c[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
        f = res / (2.0 * np.tan(0.6))
        cam = Camera(world_to_camera=w2c, width=res, height=res, fx=f, fy=f, cx=res / 2, cy=res / 2)
        img = np.array(render(g, cam).rgb, dtype=np.float32)
        views.append(View(name=f"view{i}", camera=cam, image_path=Path(f"view{i}"), loader=_MemoryLoader(img)))
    rng = np.random.default_rng(1)
    points = (scene["means"] + rng.normal(0.0, 0.01, scene["means"].shape)).astype(np.float32)
    return Dataset(root=Path(f"synthetic_{res}_{n}"), layout="blender", train=views, test=[], points_xyz=points,
                   points_rgb=np.full_like(points, 0.5), background=np.zeros(3, np.float32), color_space="linear")


def case_setup(case: str):
    """(dataset, TrainConfig, label) of a case name."""
    from mi_gaussians.config import TrainConfig

    if ":" in case:
        res, n = (int(x) for x in case.split(":"))
        cfg = TrainConfig()
        cfg = dataclasses.replace(cfg, densify=dataclasses.replace(cfg.densify, densify_until_iter=0),
                                  checkpoint_every=10 ** 9, eval_every=0)
        return synthetic_dataset(res, n), cfg, f"synthetic {res}x{res}, {n:,} Gaussians"
    from train import DATA, DATASETS

    from mi_gaussians.data.dataset import load_dataset

    if case not in DATASETS:
        raise SystemExit(f"unknown case {case!r}: RES:N or one of {', '.join(DATASETS)}")
    folder, r, bg, what = DATASETS[case]
    if not (DATA / folder).exists():
        return None
    ds = load_dataset(DATA / folder, resolution=r, background=bg)
    cfg = dataclasses.replace(TrainConfig(), checkpoint_every=10 ** 9, eval_every=0)
    return ds, cfg, f"{case} ({what})"


class GpuBusy:
    """NVML's GPU utilization polled every 20 ms by a thread between ``start()`` and ``stop()`` (pynvml, from the
    nvidia-ml-py package that PyTorch machines carry); ``stop()`` returns the mean after ``skip`` seconds."""

    def __init__(self):
        import pynvml

        pynvml.nvmlInit()
        self._nvml = pynvml
        self._handle = pynvml.nvmlDeviceGetHandleByIndex(0)

    def start(self):
        import threading

        self._samples, self._t0, self._stop = [], time.perf_counter(), threading.Event()

        def poll():
            while not self._stop.wait(0.02):
                u = self._nvml.nvmlDeviceGetUtilizationRates(self._handle).gpu
                self._samples.append((time.perf_counter() - self._t0, u))

        self._thread = threading.Thread(target=poll, daemon=True)
        self._thread.start()

    def stop(self, skip: float = 0.3) -> float:
        self._stop.set()
        self._thread.join()
        kept = [u for t, u in self._samples if t >= skip] or [u for _, u in self._samples]
        return statistics.fmean(kept) if kept else float("nan")


def measure(ds, cfg, warmup: int, iterations: int, rounds: int, busy: int = 0, profile: bool = False,
            loops: tuple = (True, False)) -> dict:
    """Both loops on the same dataset and schedule, interleaved: ``rounds`` timed passes of ``iterations`` each,
    frozen and traced taking turns (a VM's speed drifts over minutes: timing one loop after the other would credit
    the drift to the second), then a kernel-history pass and a blocking pass of each. Returns {freeze: row}."""
    import drjit as dr

    from mi_gaussians.optim.trainer import Trainer

    total = warmup + (rounds + 2) * iterations + 2 + busy
    meter = GpuBusy() if busy else None
    with tempfile.TemporaryDirectory() as tmp:
        trainers = {freeze: Trainer(ds, dataclasses.replace(cfg, freeze=freeze, optim=dataclasses.replace(
            cfg.optim, iterations=total)), Path(tmp) / str(freeze), progress=False) for freeze in loops}

        def run(tr, k):
            for _ in range(k):
                tr.advance()
            tr._resolve()
            dr.sync_thread()

        rows = {freeze: {"seconds": 0.0, "syncs": 0} for freeze in trainers}
        for tr in trainers.values():
            run(tr, warmup)
        for _ in range(rounds):
            for freeze, tr in trainers.items():
                syncs0 = tr.loop.syncs
                t0 = time.perf_counter()
                run(tr, iterations)
                rows[freeze]["seconds"] += time.perf_counter() - t0
                rows[freeze]["syncs"] += tr.loop.syncs - syncs0
        for freeze, tr in trainers.items():
            row = rows[freeze]
            with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
                dr.kernel_history()
                run(tr, iterations)
                history = dr.kernel_history()
                with dr.scoped_set_flag(dr.JitFlag.LaunchBlocking, True):
                    run(tr, 1)                  # (the blocking flag is part of a recording's key: record it first)
                    dr.kernel_history()
                    gaps = []
                    for _ in range(iterations):
                        t0 = time.perf_counter()
                        tr.advance()
                        wall_ms = 1e3 * (time.perf_counter() - t0)
                        gaps.append(wall_ms - sum(k.get("execution_time", 0.0) for k in dr.kernel_history()))
                    run(tr, 0)
            if profile and freeze:
                from kernel_profile import history_table

                row["profile"] = history_table(history, per=iterations)
            if meter is not None:
                meter.start()
                t0 = time.perf_counter()
                run(tr, busy)
                row["busy_it_s"] = busy / (time.perf_counter() - t0)
                row["busy"] = meter.stop()
            measured = rounds * iterations
            row.update(it_s=measured / row["seconds"], ms=1e3 * row["seconds"] / measured,
                       host_ms=max(0.0, statistics.median(gaps)), host_mean_ms=max(0.0, statistics.fmean(gaps)),
                       kernel_ms=sum(k.get("execution_time", 0.0) for k in history) / iterations,
                       kernels=len(history) / iterations, syncs=row["syncs"] / measured, gaussians=tr.params.n,
                       recordings=tr.train_step.recordings, overflows=tr.loop.overflows)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--cases", nargs="+", default=["200:50000", "800:300000"],
                    help="RES:N synthetic cases and/or dataset names of benchmarks/train.py")
    ap.add_argument("--iterations", type=int, default=30, help="iterations per pass")
    ap.add_argument("--rounds", type=int, default=3, help="timed passes per loop, the loops taking turns")
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--busy", type=int, default=0, metavar="K",
                    help="CUDA: K more iterations per loop with NVML's GPU utilization polled (needs pynvml)")
    ap.add_argument("--profile", action="store_true", help="where the frozen step's device time goes")
    ap.add_argument("--loops", nargs="+", default=["frozen", "traced"], choices=("frozen", "traced"),
                    help="which loops to run (default both, taking turns)")
    args = ap.parse_args(argv)
    if args.busy and not args.variant.startswith("cuda"):
        raise SystemExit("train_speed.py: --busy reads the GPU's utilization: it needs a cuda_* variant")

    import mitsuba as mi

    mi.set_variant(args.variant)
    import drjit as dr

    import mi_gaussians  # noqa: F401

    print(f"variant {args.variant}, {dr.thread_count()} threads; {args.rounds} passes of {args.iterations} "
          f"iterations per loop, taking turns, after {args.warmup} of warm-up")
    head = ("| case | loop | it/s | ms/it | host ms/it | host mean | kernel ms/it | kernels/it | syncs/it | Gaussians "
            "| recordings | ratio | GPU busy (it/s) |")
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    profiles = []
    for case in args.cases:
        setup = case_setup(case)
        if setup is None:
            print(f"| {case} | skipped: dataset not in ../shared/data |")
            continue
        ds, cfg, label = setup
        loops = tuple(loop == "frozen" for loop in args.loops)
        rows = measure(ds, cfg, args.warmup, args.iterations, args.rounds, args.busy, args.profile, loops)
        for freeze in loops:
            r = rows[freeze]
            ratio = f"{rows[True]['it_s'] / rows[False]['it_s']:.2f}x" if freeze and len(rows) == 2 else ""
            busy = f"{r['busy']:.0f} % ({r['busy_it_s']:.0f})" if "busy" in r else "-"
            print(f"| {label} | {'frozen' if freeze else 'traced'} | {r['it_s']:.1f} | {r['ms']:.2f} | "
                  f"{r['host_ms']:.2f} | {r['host_mean_ms']:.2f} | {r['kernel_ms']:.2f} | {r['kernels']:.0f} "
                  f"| {r['syncs']:.2f} | {r['gaussians']:,} | {r['recordings']} | {ratio} | {busy} |", flush=True)
        if "profile" in rows.get(True, {}):
            profiles.append(f"\n{label}, frozen step, per iteration:\n{rows[True]['profile']}")
    print("\n".join(profiles))
    return 0


if __name__ == "__main__":
    sys.exit(main())
