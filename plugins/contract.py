"""The XML contract of the ``gaussian_splatting`` integrator: its plugin name and the parameters it reads.

Declared once, here, for the integrator (:mod:`.splat_integrator`, which needs a Mitsuba variant to import) and for
the code that writes scenes using it (:mod:`.scene_xml`, which does not)."""

INTEGRATOR = "gaussian_splatting"
BACKGROUND, SH_DEGREE, DEPTH_AOV, COLOR_SPACE = "background", "sh_degree", "depth_aov", "color_space"
ANTIALIASED = "antialiased"
COLOR_SPACES = ("linear", "srgb")
