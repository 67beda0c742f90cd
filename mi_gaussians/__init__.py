"""mi-gaussians: 3D Gaussian Splatting as a Mitsuba 3 plugin.

Importing this package registers its Mitsuba plugins for the active variant (and for every variant selected later
with ``mi.set_variant``), exactly as Mitsuba's own Python plugins do, and does nothing else.

    import mitsuba as mi; mi.set_variant("llvm_ad_rgb")   # or cuda_ad_rgb
    import mi_gaussians as mig
    g = mig.Gaussians.load_ply("model.ply")
    cam = mig.Camera.from_json("cam.json")
    ds = mig.load_dataset("path/to/scene")
"""

__version__ = "0.1.0"

from .data.camera import Camera
from .data.dataset import Dataset, View, load_dataset
from .model.gaussians import Gaussians
from .raster.rasterize import RenderOutput, render
from . import plugins as _plugins

_plugins.install()

__all__ = ["Camera", "Dataset", "View", "load_dataset", "RenderOutput", "render", "Gaussians", "__version__"]
