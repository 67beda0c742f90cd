"""Which JIT kernels a piece of code launches, window by window: the check that per-view values (images, cameras,
backgrounds, lambdas) travel as opaque arrays and never become kernel literals.

Kernels are told apart by their hash, not by Dr.Jit's ``cache_hit``: that flag also counts hits in the on-disk kernel
cache (``~/.drjit``), so a kernel specialized on a value that any earlier run on the machine had seen read as a hit,
and such a test failed only on a machine (or variant) meeting the value for the first time: a clean CI machine, a
first CUDA run. A kernel with a value baked in has a new hash for every new value, whatever the caches hold."""

from __future__ import annotations

import gc

import drjit as dr


class KernelLog:
    """Records the JIT kernels launched inside ``with KernelLog() as log:``; ``log.cut()`` closes a window.

    The history flag is set on entry (JIT flags are part of a ``dr.freeze`` recording's key, so warm-up calls belong
    inside the block), pending work is evaluated first and the garbage collector is off inside (nothing freed at a
    random moment may change what the measured kernels contain)."""

    def __enter__(self) -> "KernelLog":
        dr.eval()
        gc.collect()
        gc.disable()
        self._flag = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()                     # clear
        self.windows: list[list[tuple[int, str]]] = []
        return self

    def __exit__(self, *exc) -> None:
        dr.set_flag(dr.JitFlag.KernelHistory, self._flag)
        gc.enable()

    def cut(self) -> list[tuple[int, str]]:
        """Closes the current window: its JIT kernels as (size, hash), in launch order."""
        self.windows.append([(k["size"], k["hash"]) for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT])
        return self.windows[-1]

    def unseen(self, i: int) -> list[tuple[int, str]]:
        """The kernels of window ``i`` whose hash no earlier window launched."""
        seen = {h for w in self.windows[:i] for _, h in w}
        return [k for k in self.windows[i] if k[1] not in seen]
