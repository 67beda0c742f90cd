"""Import direction: every module of ``mi_gaussians/`` and ``plugins/`` imports only from its own layer or lower.

The layers, bottom to top (a module may import from its own layer or a lower one, never a higher one)::

    0    base          config, setting_values, setting_effects, io_utils, _libllvm, errors, memory, drjit_utils,
                       conventions, imwrite, image_ops, run_folder (the names and the lock of a run's output folder: the trainer, the
                       report and the CLI share them)
    0.5  metrics       metrics (scores images; sits on the base only)
    1    data          mi_gaussians.data.*
    2    model         mi_gaussians.model.*
    3    raster        mi_gaussians.raster.*
    4    plugins       plugins/ (installed as mi_gaussians.plugins)
    5    training      evaluate, report, runs (what a run trained on, how to render its model), mi_gaussians.optim.*
    5.5  cluster       mi_gaussians.cluster.* (Ray: sweeps, references rendered by workers)
    6    front ends    cli (a package: one module per command), viewer, and the package itself
                       (mi_gaussians/__init__.py, the public face)

Every import is collected with ``ast``, those inside functions and ``if TYPE_CHECKING`` blocks included, absolute
(``mi_gaussians.x``) and relative (``from ..x import y``, ``from . import x``). A module missing from the table fails
the test: a new module must be given its layer here.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "mi_gaussians"

#: Module name (or package prefix) -> layer. The longest matching prefix wins.
LAYERS: dict[str, float] = {
    # 0: base
    "mi_gaussians.config": 0,
    "mi_gaussians.setting_values": 0,
    "mi_gaussians.io_utils": 0,
    "mi_gaussians._libllvm": 0,
    "mi_gaussians.drjit_utils": 0,
    "mi_gaussians.conventions": 0,
    "mi_gaussians.imwrite": 0,
    "mi_gaussians.image_ops": 0,
    "mi_gaussians.image_walk": 0,
    "mi_gaussians.run_folder": 0,
    "mi_gaussians.errors": 0,
    "mi_gaussians.memory": 0,
    "mi_gaussians.setting_effects": 0,
    # 0.5: metrics, on the base only
    "mi_gaussians.metrics": 0.5,
    # 1..4
    "mi_gaussians.data": 1,
    "mi_gaussians.model": 2,
    "mi_gaussians.raster": 3,
    "mi_gaussians.plugins": 4,
    # 5: training and evaluation
    "mi_gaussians.evaluate": 5,
    "mi_gaussians.report": 5,
    "mi_gaussians.optim": 5,
    # 6: front ends and the package's public face
    "mi_gaussians.runs": 5,
    # 5.5: beyond one process (Ray), above the training it distributes
    "mi_gaussians.cluster": 5.5,
    "mi_gaussians.cli": 6,
    "mi_gaussians.viewer": 6,
    "mi_gaussians.viewer_entries": 6,
    "mi_gaussians": 6,
}


_SOURCE_DIRS = ((ROOT / "mi_gaussians", PACKAGE), (ROOT / "plugins", f"{PACKAGE}.plugins"))


def layer_of(module: str) -> float | None:
    """The layer of a module of the package (longest prefix of :data:`LAYERS`), None when none matches."""
    parts = module.split(".")
    for i in range(len(parts), 0, -1):
        key = ".".join(parts[:i])
        if key in LAYERS:
            return LAYERS[key]
    return None


def package_modules() -> dict[str, Path]:
    """Module name -> file, for every ``.py`` file of the package (``plugins/`` named ``mi_gaussians.plugins``)."""
    out = {}
    for folder, prefix in _SOURCE_DIRS:
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder).with_suffix("").parts
            if rel[-1] == "__init__":
                rel = rel[:-1]
            out[".".join((prefix, *rel))] = path
    return out


def imports_of(source: str, module: str, is_package: bool, known: set[str]) -> list[tuple[int, str]]:
    """(line, imported module) for every import of a ``mi_gaussians`` module in ``source``, at any depth.

    ``from X import name`` is taken as the submodule ``X.name`` when that is a module in ``known``, else as ``X``."""
    pkg = module if is_package else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = pkg.split(".")
                if node.level - 1 > len(parts) - 1:
                    raise ValueError(f"{module}:{node.lineno}: relative import beyond the top-level package")
                base = ".".join(parts[: len(parts) - (node.level - 1)])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.append((node.lineno, sub if sub in known else base))
    return sorted((line, t) for line, t in out if t == PACKAGE or t.startswith(PACKAGE + "."))


def upward_imports(modules: dict[str, Path]) -> tuple[list[str], int]:
    """(violations as "file:line: importer (layer) -> target (layer)", number of package imports checked)."""
    known = set(modules)
    bad, count = [], 0
    for module, path in modules.items():
        if module == PACKAGE:                     # the public face may import anything (checked below)
            continue
        own = layer_of(module)
        for line, target in imports_of(path.read_text(), module, path.name == "__init__.py", known):
            count += 1
            tl = layer_of(target)
            if tl is not None and tl > own:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {module} (layer {own}) -> {target} (layer {tl})")
    return bad, count


# ----------------------------------------------------------------------------------------------------------- tests
def test_every_module_has_a_layer():
    modules = package_modules()
    missing = [f"{p.relative_to(ROOT)} ({m})" for m, p in modules.items() if layer_of(m) is None]
    assert not missing, "modules missing from LAYERS in tests/test_layering.py: " + ", ".join(missing)


def test_imports_point_down():
    modules = package_modules()
    bad, count = upward_imports(modules)
    # not vacuous: the walk found the package and its imports (about 40 modules, 100+ package imports today)
    assert len(modules) >= 30 and count >= 80, (len(modules), count)
    for m in ("mi_gaussians.metrics", "mi_gaussians.image_ops", "mi_gaussians.raster.projection",
              "mi_gaussians.plugins.splat_integrator", "mi_gaussians.optim.losses"):
        assert m in modules
    assert not bad, "imports pointing to a higher layer:\n" + "\n".join(bad)



def test_package_init_only_imports_and_registers():
    """``mi_gaussians/__init__.py`` is exempt from the layers, so it must do nothing but import, name its exports and
    register the Mitsuba plugins."""
    tree = ast.parse((ROOT / "mi_gaussians" / "__init__.py").read_text())
    for i, node in enumerate(tree.body):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if i == 0 and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            continue                                                        # the docstring
        if isinstance(node, ast.Assign) and all(isinstance(t, ast.Name) and t.id in ("__version__", "__all__")
                                                for t in node.targets):
            continue
        if (isinstance(node, ast.Expr) and isinstance(node.value, ast.Call)
                and isinstance(node.value.func, ast.Attribute) and node.value.func.attr in ("install", "register")):
            continue                                                        # _plugins.install()
        pytest.fail(f"mi_gaussians/__init__.py:{node.lineno}: {ast.dump(node)[:80]} is neither an import nor the "
                    "plugin registration")


# ------------------------------------------------------------------------------------------------------ self-tests
_KNOWN = {"mi_gaussians", "mi_gaussians.metrics", "mi_gaussians.optim", "mi_gaussians.optim.losses",
          "mi_gaussians.data", "mi_gaussians.data.camera", "mi_gaussians.image_ops", "mi_gaussians.plugins"}


def test_self_test_function_level_relative_import_is_found():
    src = ("import numpy as np\n"
           "from .image_ops import ssim\n"
           "def f():\n"
           "    if True:\n"
           "        from .optim.losses import photometric_loss\n"
           "    import mi_gaussians.cli\n"
           "    from mi_gaussians.optim import losses\n"
           "    from . import plugins\n")
    got = imports_of(src, "mi_gaussians.metrics", False, _KNOWN)
    assert got == [(2, "mi_gaussians.image_ops"), (5, "mi_gaussians.optim.losses"), (6, "mi_gaussians.cli"),
                   (7, "mi_gaussians.optim.losses"), (8, "mi_gaussians.plugins")]
    assert [t for _, t in got if layer_of(t) > layer_of("mi_gaussians.metrics")] == [
        "mi_gaussians.optim.losses", "mi_gaussians.cli", "mi_gaussians.optim.losses", "mi_gaussians.plugins"]


def test_self_test_upward_import_is_reported(tmp_path, monkeypatch):
    (tmp_path / "mi_gaussians" / "data").mkdir(parents=True)
    (tmp_path / "mi_gaussians" / "__init__.py").write_text("from .data import camera\n")
    (tmp_path / "mi_gaussians" / "imwrite.py").write_text("import numpy\n")
    (tmp_path / "mi_gaussians" / "data" / "__init__.py").write_text("")
    (tmp_path / "mi_gaussians" / "data" / "camera.py").write_text(
        "from ..imwrite import write_png\n\ndef load():\n    from ..raster.rasterize import render\n")
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    monkeypatch.setitem(globals(), "_SOURCE_DIRS", ((tmp_path / "mi_gaussians", PACKAGE),
                                                    (tmp_path / "plugins", f"{PACKAGE}.plugins")))
    modules = package_modules()
    assert set(modules) == {"mi_gaussians", "mi_gaussians.imwrite", "mi_gaussians.data", "mi_gaussians.data.camera"}
    bad, count = upward_imports(modules)
    assert count == 2
    assert bad == [f"{Path('mi_gaussians/data/camera.py')}:4: mi_gaussians.data.camera (layer 1) -> "
                   "mi_gaussians.raster.rasterize (layer 3)"]
