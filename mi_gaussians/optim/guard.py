"""The divergence guard: every trained quantity finite, or the run stops with one line naming what diverged.

A run learns its Gaussians (six parameter groups), and with ``--pose-opt`` / ``--exposure`` a correction per
training camera or image; each has Adam moments. A rate too large for its group makes the group non-finite. The loss
alone does not always show it: a camera whose correction became NaN sees nothing, and its loss stays finite (issue
54). So at every synchronization of the training loop (every ``trainer.SYNC_EVERY`` iterations, and before every
checkpoint) :func:`check` reads one flag per group (values and moments all finite, reduced on the device) and raises
:class:`TrainingDiverged` naming the group, the iterations between which it diverged and the setting that drives it;
the trainer never writes a checkpoint past that point, so the last good one stays (``cli.errors.EXIT_DIVERGED``).
"""

from __future__ import annotations

import drjit as dr

from ..config import OptimConfig

#: parameter group -> (what a person calls it, the settings whose size drives its steps)
GROUPS = {
    "means": ("the Gaussians' positions", ("optim.position_lr_init",)),
    "scales": ("the Gaussians' scales", ("optim.scaling_lr",)),
    "rotations": ("the Gaussians' rotations", ("optim.rotation_lr",)),
    "opacities": ("the Gaussians' opacities", ("optim.opacity_lr",)),
    "sh_dc": ("the Gaussians' colours (SH band 0)", ("optim.feature_lr",)),
    "sh_rest": ("the Gaussians' colours (SH bands 1-3)", ("optim.feature_lr",)),
    "pose": ("the camera pose corrections (--pose-opt)", ("optim.pose_opt_lr", "optim.pose_opt_lr_decay")),
    "exposure": ("the exposure compensation (--exposure)",
                 ("optim.exposure_lr_init", "optim.exposure_grid_lr", "optim.exposure_grid_tv")),
}


class TrainingDiverged(RuntimeError):
    """The loss or a trained quantity became NaN/Inf."""


def flags(*owners) -> dict[str, object]:
    """The finiteness flags (1-element device ``mi.Bool``) of every group of ``owners`` (objects with a ``finite()``
    method: the Gaussians' optimizer, pose corrections, exposure compensation; None is skipped)."""
    out = {}
    for owner in owners:
        if owner is not None:
            out.update(owner.finite())
    return out


def _setting_values(names, cfg: OptimConfig) -> str:
    parts = []
    for name in names:
        field = name.split(".", 1)[1]
        if hasattr(cfg, field):
            parts.append(f"{name} = {getattr(cfg, field):g}")
    return ", ".join(parts)


def check(groups: dict, cfg: OptimConfig, since: int, step: int, checkpoint) -> None:
    """Raise :class:`TrainingDiverged` when a flag of ``groups`` (:func:`flags`) is False: the first such group, that
    it became non-finite after iteration ``since`` and by ``step``, the settings that drive it with their values, and
    that ``checkpoint`` (the last good one) is kept."""
    if not groups:
        return
    dr.eval(*groups.values())
    bad = [key for key, ok in groups.items() if not bool(ok[0])]
    if not bad:
        return
    what, settings = GROUPS.get(bad[0], (bad[0], ()))
    drive = _setting_values(settings, cfg)
    others = f" (also: {', '.join(GROUPS.get(k, (k,))[0] for k in bad[1:])})" if len(bad) > 1 else ""
    raise TrainingDiverged(f"{what} became non-finite between iterations {since} and {step}{others}"
                           f"{'; driven by ' + drive if drive else ''}: lower it; the last good checkpoint "
                           f"({checkpoint}) is kept")
