"""Installation facts: libLLVM >= 16 is selected before Dr.Jit starts (and never over the user's choice), the
plugins install as ``mi_gaussians.plugins`` (not a generic top-level ``plugins``), and importing registers them."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile

import pytest

from mi_gaussians import _libllvm

# The one-line crash repro of drjit-notes.md: with libLLVM 15 this aborts the whole process ("Cannot select").
CRASH_REPRO = ("import drjit as dr; from drjit.llvm import Float; "
               "print(dr.minimum(dr.arange(Float, 1000) * 2, 0.9999)[3]); "
               "print('llvm', '.'.join(map(str, dr.detail.llvm_version())))")


def _python(code: str, env=None):
    e = dict(os.environ if env is None else env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=e,
                          cwd=tempfile.gettempdir())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the bundled libLLVM is for Linux")
def test_fresh_interpreter_selects_a_new_libllvm_and_min_max_work():
    env = dict(os.environ)
    env.pop("DRJIT_LIBLLVM_PATH", None)        # a fresh shell: only the installed .pth sets it
    res = _python(CRASH_REPRO, env)
    assert res.returncode == 0, f"Dr.Jit aborted on dr.minimum (rc {res.returncode}): {res.stderr[-500:]}"
    lines = res.stdout.split()
    assert abs(float(lines[0]) - 0.9999) < 1e-6
    major = int(res.stdout.split("llvm")[1].split(".")[0])
    assert major >= 16


def test_pth_file_is_installed_next_to_the_package():
    candidates = [os.path.join(p, "mi_gaussians_llvm.pth") for p in sys.path if p]
    assert any(os.path.exists(c) for c in candidates), "mi_gaussians_llvm.pth is not on any site path"


def test_user_setting_is_never_overridden(tmp_path):
    env = {"DRJIT_LIBLLVM_PATH": "/my/own/libLLVM.so"}
    assert _libllvm.select_libllvm(env) == "/my/own/libLLVM.so"
    assert env["DRJIT_LIBLLVM_PATH"] == "/my/own/libLLVM.so"
    # and at interpreter start-up (the .pth runs before any user code)
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(tmp_path / "user-choice.so"))
    res = _python("import os; print(os.environ['DRJIT_LIBLLVM_PATH'])", env)
    assert res.stdout.strip() == str(tmp_path / "user-choice.so")


def test_select_sets_an_existing_library_when_unset():
    env = {}
    path = _libllvm.select_libllvm(env)
    if path is None:
        pytest.skip("karellen-llvm-core is not installed in this environment")
    assert os.path.exists(path) and env["DRJIT_LIBLLVM_PATH"] == path


def test_plugins_import_under_the_package_name():
    import mi_gaussians.plugins as p

    assert p.__name__ == "mi_gaussians.plugins"
    res = _python("import importlib.util; print(importlib.util.find_spec('plugins') is None)")
    assert res.stdout.strip() == "True", "a generic top-level 'plugins' package is importable"


def test_import_registers_for_the_active_variant_only_once_set():
    code = ("import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); import mi_gaussians; "
            "print(mi.load_dict({'type': 'gaussian_splatting'}))")
    res = _python(code)
    assert res.returncode == 0 and "GaussianSplattingIntegrator" in res.stdout, res.stderr[-800:]
    # importing before any variant is set, then selecting one, also works (variant callback)
    code = ("import mitsuba as mi; import mi_gaussians; mi.set_variant('llvm_ad_rgb'); "
            "print(mi.load_dict({'type': 'gaussian_splatting'}))")
    res = _python(code)
    assert res.returncode == 0 and "GaussianSplattingIntegrator" in res.stdout, res.stderr[-800:]


def test_the_source_tree_imports_like_the_installed_package():
    """``python -c`` from the repository root (or a Ray worker started there) finds the source tree's ``mi_gaussians``
    before the installed one: it must import with its plugins, not fail half-way (``mi_gaussians/plugins`` links to
    ``plugins/``)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = ("import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); import mi_gaussians, mi_gaussians.plugins as p; "
            "print(p.__file__); print(mi.load_dict({'type': 'gaussian_splatting'}))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=root)
    assert res.returncode == 0 and "GaussianSplattingIntegrator" in res.stdout, res.stderr[-800:]
    assert res.stdout.splitlines()[0].startswith(os.path.join(root, "mi_gaussians", "plugins"))
