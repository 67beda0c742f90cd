"""What a finished run writes (:meth:`.trainer.Trainer.finish`): the model, the test views' renders, comparisons and
scores (``metrics.json``), the history and its curves, the exposure compensation and refined cameras it learned."""

from __future__ import annotations

import dataclasses

import numpy as np

from .. import report, run_folder
from ..evaluate import PROTOCOLS, depth_error, evaluate_views, scores_report
from .compensation import save_compensation
from .pose import save_refined_cameras

#: A --pose-opt run whose corrections moved the cameras further than this on average says so (a rate too large
#: throws the cameras around while the loss stays finite: issue 54).
LARGE_CORRECTION_DEGREES = 10.0
LARGE_CORRECTION_OF_EXTENT = 0.2


def write_outputs(tr) -> dict:
    """The final outputs of trainer ``tr`` at its last iteration: PLY, test renders and comparisons, metrics.json,
    history and curves (and, with --exposure / --pose-opt, what the run learned about its training images). A stop
    asked for while they are written (before metrics.json, the run's last word) stops the run at its last
    iteration."""
    g = tr.gaussians
    tr._stop_if_asked()
    g.save_ply(tr.out / run_folder.MODEL)
    views = tr.ds.test if tr.ds.test else tr.ds.train[:1]
    if not tr.ds.test and tr.poses is not None:     # (a training view: through its refined camera, as eval)
        views = [dataclasses.replace(views[0], camera=tr.poses.cameras([views[0].camera])[0])]
    scores, note = evaluate_views(g, views, tr.background, cfg=tr.cfg.raster, keep_images=True,
                                  color_space=tr.ds.color_space)
    tr._stop_if_asked()
    report.write_view_outputs(tr.out, scores, tr.ds.color_space)
    tr.loop.close(tr.elapsed)
    metrics = {
        "split": "test" if tr.ds.test else "train (no test views)",
        "protocol": PROTOCOLS["full"],
        **scores_report(scores, note),
        "gaussians": g.n,
        "extent": round(tr.extent, 6),     # (the length the run's length rules were fractions of: data.extent)
        "length_scale": round(tr.extent, 6),     # (the same, by the name info and the docs give it)
        "iterations": tr.step,
        "training_seconds": round(tr.elapsed, 3),
        "iterations_per_second": round(tr.step / tr.elapsed, 3) if tr.elapsed > 0 else None,
        "loop": tr.loop.to_dict(),
    }
    if tr.exposure is not None:            # (the transforms belong to the training images: beside the model)
        half, _ = evaluate_views(g, views, tr.background, cfg=tr.cfg.raster, color_space=tr.ds.color_space,
                                 protocol="half")
        metrics["half_image"] = {"protocol": PROTOCOLS["half"], **scores_report(half, note)}
        save_compensation(tr.exposure, tr.out, [v.name for v in tr.ds.train])
    if tr.poses is not None or any(c is not v.camera for c, v in zip(tr.given_cameras, tr.ds.train)):
        metrics["poses"] = pose_report(tr)
    depth = depth_error(g, views, cfg=tr.cfg.raster)
    if depth is not None:
        metrics["depth_mae"], metrics["depth_coverage"] = depth["depth_mae"], round(depth["coverage"], 6)
    tr._stop_if_asked()
    report.write_json(tr.out / run_folder.METRICS, metrics)
    report.write_json(tr.out / run_folder.HISTORY, tr.history.to_dict())
    report.plot_curves(tr.out / run_folder.CURVES, tr.history.to_dict())
    return metrics


def pose_report(tr) -> dict:
    """The training cameras' mean errors against the given ones (``tr.given_cameras``), as the run started and as it
    ends (refined: ``--pose-opt``), and the refined cameras written beside the model."""
    from ..data.pointcloud import camera_extent
    from ..data.pose_noise import pose_errors, reprojection_error, reprojection_points

    extent = camera_extent(np.stack([c.center for c in tr.given_cameras]))[1]    # (the given cameras' extent)
    start = [v.camera for v in tr.ds.train]
    end = start if tr.poses is None else tr.poses.cameras(start)
    if tr.poses is not None:
        save_refined_cameras(tr.out, end)
    (r0, d0), (r1, d1) = pose_errors(start, tr.given_cameras), pose_errors(end, tr.given_cameras)
    out = {"against": "the training cameras as the dataset gives them", "optimized": tr.poses is not None,
           "rotation_error_degrees": {"start": round(r0, 6), "end": round(r1, 6)},
           "translation_error": {"start": round(d0, 8), "end": round(d1, 8)},
           "translation_error_of_extent": {"start": round(d0 / extent, 8), "end": round(d1 / extent, 8)}}
    if tr.poses is not None:
        moved_deg, moved = pose_errors(end, start)     # (how far the corrections took the cameras)
        out["correction"] = {"rotation_degrees": round(moved_deg, 6), "translation_of_extent": round(moved / extent, 8)}
        if moved_deg > LARGE_CORRECTION_DEGREES or moved / extent > LARGE_CORRECTION_OF_EXTENT:
            out["note"] = (f"the pose corrections moved the training cameras by {moved_deg:.1f} degrees and "
                           f"{moved / extent:.2f} of their spread on average: far more than calibration errors; "
                           f"optim.pose_opt_lr = {tr.cfg.optim.pose_opt_lr:g} may be too large for this scene")
    points = tr.ds.points_xyz      # (the run's initial points, in the given cameras' frame: the scene's points)
    used = reprojection_points(points)       # (taken once, for both ends)
    p0, p1 = (reprojection_error(c, tr.given_cameras, used) for c in (start, end))
    if p0 is not None and p1 is not None:
        subset = "" if len(used) == len(points) else f" (an evenly strided {len(used):,} of them)"
        out["reprojection_error_pixels"] = {"start": round(p0, 6), "end": round(p1, 6),
                                            "of": f"the run's {len(points):,} initial points{subset}"}
    return out
