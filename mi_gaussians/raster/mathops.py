"""Float min/max/clamp written with ``dr.select``.

``dr.minimum/maximum/clip`` on floats abort the process when Dr.Jit JIT-compiles with libLLVM 15 (see
``drjit-notes.md``). The package selects a newer libLLVM at start-up, but a user may point ``DRJIT_LIBLLVM_PATH`` at
an old one; these helpers compile to the same select instructions on every LLVM and on CUDA, and their gradient
follows the selected branch (zero for the clamped side), like the reference rasterizer's ``min``/``max``.
"""

import drjit as dr


def fmin(a, b):
    return dr.select(a < b, a, b)


def fmax(a, b):
    return dr.select(a > b, a, b)


def fclamp(x, lo, hi):
    return fmin(fmax(x, lo), hi)
