"""Select a libLLVM >= 16 for Dr.Jit's LLVM backend, before Dr.Jit is imported.

Dr.Jit 1.5 aborts the process on ``dr.minimum/maximum/clip`` over floats when it JIT-compiles with libLLVM 15
(the system library of Debian 12 / Ubuntu 22.04): ``LLVM ERROR: Cannot select: ... fminimum``. Dr.Jit reads the
library path once, when its LLVM backend starts, so the choice has to be made before ``mi.set_variant('llvm_*')``,
which is earlier than ``import mi_gaussians`` in ordinary user code. The installed ``mi_gaussians_llvm.pth`` calls
:func:`select_libllvm` at interpreter start-up; it only touches the standard library and the file system.

Rules: a user's own ``DRJIT_LIBLLVM_PATH`` is never overridden; otherwise the libLLVM shipped by the
``karellen-llvm-core`` wheel (installed under ``<prefix>/lib``) is selected when present.
"""

import os
import sys

ENV_VAR = "DRJIT_LIBLLVM_PATH"


def candidate_paths():
    """libLLVM files that the karellen-llvm-core wheel may have installed, most specific first."""
    prefixes = [sys.prefix]
    try:
        import site

        user_base = site.getuserbase()
        if user_base:
            prefixes.append(user_base)
    except Exception:  # pragma: no cover - site is always importable in CPython
        pass
    return [os.path.join(p, "lib", "libLLVM.so") for p in prefixes]


def select_libllvm(environ=None):
    """Set ``DRJIT_LIBLLVM_PATH`` in ``environ`` (default ``os.environ``) unless the user already set it.

    Returns the path in effect afterwards (or ``None`` when nothing was found and nothing was set)."""
    environ = os.environ if environ is None else environ
    if environ.get(ENV_VAR):
        return environ[ENV_VAR]
    for path in candidate_paths():
        if os.path.exists(path):
            environ[ENV_VAR] = os.path.realpath(path)
            return environ[ENV_VAR]
    return None
