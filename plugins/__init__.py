"""Mitsuba plugins of mi-gaussians (installed as ``mi_gaussians.plugins``).

:func:`register` registers every plugin for the active Mitsuba variant; it is idempotent. :func:`install` does that
and also registers them again whenever ``mi.set_variant`` selects another variant (Mitsuba re-imports its own Python
plugins the same way). Only JIT variants with automatic differentiation (``llvm_ad_*``, ``cuda_ad_*``) get them:
the rasterizer is written in Dr.Jit and needs AD for its gradients.
"""

from __future__ import annotations

import importlib

import mitsuba as mi

# Each module defines ``register()`` that calls mi.register_integrator / mi.register_shape for the active variant.
_PLUGIN_MODULES: tuple[str, ...] = ("splat_integrator",)


def supported_variant(variant: str | None) -> bool:
    return bool(variant) and (variant.startswith("llvm_ad_") or variant.startswith("cuda_ad_"))


def register() -> list[str]:
    """Register the plugins for the active variant; returns the names registered (empty for other variants)."""
    if not supported_variant(mi.variant()):
        return []
    names: list[str] = []
    for mod in _PLUGIN_MODULES:
        names += importlib.import_module(f"{__name__}.{mod}").register()
    return names


def _on_variant_change(old, new):
    if new != old:
        register()


def install() -> None:
    """Register now, and after every later ``mi.set_variant`` (the callback is added once per process)."""
    register()
    mi.detail.remove_variant_callback(_on_variant_change)
    mi.detail.add_variant_callback(_on_variant_change)
