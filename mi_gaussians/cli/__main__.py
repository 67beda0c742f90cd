"""``python -m mi_gaussians.cli``: the same as ``mi-gs``."""

import sys

from . import main

sys.exit(main())
