"""The host side of the training loop that checkpoints carry besides the parameters: the history of the run (loss,
Gaussians, time, test PSNR per iteration), where its time went (:class:`LoopStats`) and the order of the training
views."""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np


@dataclass
class History:
    iteration: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    gaussians: list = field(default_factory=list)
    seconds: list = field(default_factory=list)     # training time (evaluation excluded) after each iteration
    instances: list = field(default_factory=list)   # (Gaussian, tile) pairs blended by each iteration (the work of
                                                    # its blend; absent from the checkpoints of earlier versions)
    eval_iteration: list = field(default_factory=list)
    test_psnr: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


#: The parts of a run's training time (:class:`LoopStats`): replaying frozen steps (on a GPU the call returns once
#: the kernels are queued; on the CPU it also runs most of them: each sort pass waits for the work before it), frozen
#: steps that were recorded (traced, recorded and compiled: a new model size, SH degree or capacity), waiting for
#: queued frozen steps to finish, traced iterations (the first and the refinement iterations), refinements
#: (densification, pruning, opacity resets), and the rest of the loop.
TIME_PARTS = ("frozen", "recording", "waiting", "traced", "refinement", "other")


@dataclass
class LoopStats:
    """Where a run's time went and how often the loop did its costly things (``metrics.json``'s ``loop``, carried by
    checkpoints). ``seconds`` splits the training time by :data:`TIME_PARTS`; ``outside`` holds the seconds of the
    evaluations and of saving (checkpoints, models), which are not training time. ``replayed``: frozen iterations
    thrown away by instance-capacity overflows and run again."""

    seconds: dict = field(default_factory=lambda: dict.fromkeys(TIME_PARTS, 0.0))
    recordings: int = 0
    compiles: int = 0           # kernels built during training (in no kernel cache of Dr.Jit's: a new kernel)
    cache_loads: int = 0        # kernels loaded from Dr.Jit's disk cache during training (built by an earlier run)
    overflows: int = 0
    replayed: int = 0
    traced: int = 0
    refinements: int = 0
    syncs: int = 0
    regrids: int = 0            # new tile grids chosen for the blend (on the CPU), each measured by a traced iteration
    lanes: dict = field(default_factory=dict)   # iterations per blend layout (its LaneLayout.label; raster.lanes)
    outside: dict = field(default_factory=lambda: {"evaluation": 0.0, "saving": 0.0})

    @contextmanager
    def timed(self, part: str):
        """Book the block's seconds to ``part``, a key of ``seconds`` or ``outside`` (the block may rename it:
        ``with stats.timed("frozen") as part: part[0] = "recording"``)."""
        t0, named = time.perf_counter(), [part]
        try:
            yield named
        finally:
            book = self.seconds if named[0] in self.seconds else self.outside
            book[named[0]] += time.perf_counter() - t0

    def close(self, training_seconds: float) -> None:
        """Book what the named parts did not account for of ``training_seconds`` as "other"."""
        named = sum(v for k, v in self.seconds.items() if k != "other")
        self.seconds["other"] = max(training_seconds - named, 0.0)

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["seconds"] = {k: round(v, 3) for k, v in self.seconds.items()}
        d["outside"] = {k: round(v, 3) for k, v in self.outside.items()}
        return d

    @classmethod
    def from_dict(cls, d: dict | None) -> "LoopStats":
        """(a checkpoint of an earlier version has none: counting starts again)"""
        if not d:
            return cls()
        stats = cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__ and k not in ("seconds", "outside")})
        for name in ("seconds", "outside"):
            book = getattr(stats, name)
            book.update({k: float(v) for k, v in d.get(name, {}).items() if k in book})
        return stats


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


class TrainingStopped(Exception):
    """The run was asked to stop (``Trainer.stop_signal``, e.g. by SIGTERM): it finished its iteration and wrote
    a checkpoint at ``step``, from which ``--resume`` continues."""

    def __init__(self, signum: int, step: int):
        self.signum, self.step = signum, step
        super().__init__(f"stopped at iteration {step} (signal {signum})")


@dataclass
class Pending:
    """A queued frozen iteration: its view, the random streams' states before it (to replay it) and its device
    results (loss, ok flag, the instance list's length, the instances blended, the most of them in one tile)."""

    step: int
    view: int
    host: tuple
    loss: object
    ok: object
    instances: object
    blended: object
    max_tile: object
