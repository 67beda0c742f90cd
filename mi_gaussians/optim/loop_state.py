"""The host side of the training loop that checkpoints carry besides the parameters: the history of the run (loss,
Gaussians, time, test PSNR per iteration) and the order of the training views."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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
