"""``TrainConfig``: the one home of defaults; ``with_settings`` (``mi-gs optimize --set``) parses each value as its
field's type and refuses unknown names and malformed values with a one-line message."""

from __future__ import annotations

import dataclasses

import pytest

from mi_gaussians.config import DensifyConfig, OptimConfig, TrainConfig


def test_settings_are_parsed_as_their_field_types():
    base = TrainConfig()
    cfg = base.with_settings(["densify.min_opacity=0.1", "optim.iterations=2_000", "data.background=1,0.5,0",
                              "optim.random_background=true", "seed=7", "save_iterations=2000, 5000",
                              "scene.resolution=120 80", "scene.fov=none", "scene.init=random",
                              "scene.elevation=-20,30"])
    assert cfg.densify.min_opacity == 0.1 and isinstance(cfg.densify.min_opacity, float)
    assert cfg.optim.iterations == 2000 and isinstance(cfg.optim.iterations, int)
    assert cfg.data.background == (1.0, 0.5, 0.0)
    assert cfg.optim.random_background is True
    assert cfg.seed == 7 and cfg.save_iterations == (2000, 5000)
    assert cfg.scene.resolution == (120, 80) and cfg.scene.fov is None and cfg.scene.init == "random"
    assert cfg.scene.elevation == (-20.0, 30.0)   # tuples may hold negative numbers
    # everything else untouched, the original unchanged, and the result survives config.json
    assert cfg.densify == dataclasses.replace(DensifyConfig(), min_opacity=0.1)
    assert cfg.optim == dataclasses.replace(OptimConfig(), iterations=2000, random_background=True)
    assert base == TrainConfig()
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    assert base.with_settings([]) == base
    # later assignments win
    assert base.with_settings(["seed=1", "seed=2"]).seed == 2


@pytest.mark.parametrize("text, needle", [
    ("densify.min_opacity", "expected NAME=VALUE"),
    ("=3", "expected NAME=VALUE"),
    ("densify.nope=1", "no such field (fields of densify: densify_from_iter"),
    ("nope=1", "no such field"),
    ("foo.bar=1", "no section 'foo'"),
    ("a.b.c=1", "SECTION.FIELD"),
    ("densify=1", "densify is a section"),
    ("densify.min_opacity=abc", "'abc' is not a valid float"),
    ("densify.min_opacity=nan", "not a valid float"),
    ("optim.iterations=1.5", "not a valid int"),
    ("optim.random_background=maybe", "not a valid bool"),
    ("data.background=1,1", "expected 3 comma-separated values"),
    ("densify.grad_threshold=-0.1", "must not be negative"),
    # each setting's range (config.RULES)
    ("densify.min_opacity=1.5", "must be >= 0 and < 1, got 1.5"),
    ("optim.iterations=0", "must be >= 1, got 0"),
    ("checkpoint_every=0", "must be >= 1"),
    ("mcmc.init_opacity=1", "must be > 0 and < 1"),
    ("raster.alpha_min=0", "must be > 0 and < 1, got 0"),      # the footprint is the ellipse of alpha >= alpha_min
    ("optim.sh_degree=4", "must be >= 0 and <= 3"),
    ("strategy=sgd", "'sgd' is not one of default, mcmc"),
    ("data.init=sphere", "'sphere' is not one of auto, points, triangulate, cube, frustum"),
    ("scene.resolution=8", "must be >= 16"),
    ("scene.resolution=64,64,64", "expected 1 to 2 values, got 3"),
])
def test_bad_settings_are_one_line_errors(text, needle):
    with pytest.raises(ValueError) as e:
        TrainConfig().with_settings([text])
    msg = str(e.value)
    assert needle in msg and "\n" not in msg, msg
