"""``python -m mi_gaussians.cli``: the same as ``mi-gs``."""

from . import entry_point

entry_point()
