"""Sphinx configuration of the mi-gaussians documentation.

Build (after ``pip install '.[docs]'``), warnings as errors, nothing downloaded:

    sphinx-build -W --keep-going -b html docs docs/_build/html

The reference pages (commands, training settings, the integrator's parameters, the run folder) are generated from
the code at build time by ``docs/_ext/mig_reference.py``; the Python API by autodoc.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent / "_ext"))

import mi_gaussians  # noqa: E402  (the documented package must import, and its version names the docs)

project = "mi-gaussians"
author = "the mi-gaussians developers"
copyright = "the mi-gaussians developers"
release = version = mi_gaussians.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "mig_reference",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", "**/.ipynb_checkpoints"]

# MyST: Markdown pages with Sphinx's roles and directives; headings get anchors for links between pages
myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 4

# autodoc: the public API as the code documents it (Google / NumPy sections through napoleon)
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_class_signature = "separated"       # a class's name alone; its constructor's parameters under it
autodoc_default_options = {"members": True}
napoleon_google_docstring = True
napoleon_numpy_docstring = True

# Offline: no intersphinx, no remote images or fonts; Sphinx's own search (searchindex.js) works from file://
html_theme = "furo"
html_title = f"mi-gaussians {release}"
html_static_path: list[str] = []
html_show_sourcelink = False
html_theme_options = {"navigation_with_keys": True}
pygments_style = "friendly"
