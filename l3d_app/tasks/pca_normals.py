"""pca_normals: PCA normals of a point cloud (the built-in room by default), its statistics and the
horizontal / vertical surface classification.

Normals come from :func:`l3d_app.geometry.normals.estimate_normals` (plane fit to each point's
``k`` nearest neighbours); :func:`l3d_app.geometry.surface_orientation.classify_orientation`
sorts them into horizontal (normal along ``up``), vertical (normal perpendicular to ``up``)
and other, within ``tolerance_deg``; ``preset=exercise`` uses the worked exercise's rule instead
(:func:`~l3d_app.geometry.surface_orientation.classify_by_cosine`: horizontal ``|n . up| > 0.8``, vertical
``< 0.3``, the ``exercise`` block). The class counts are printed on stdout and kept in metrics.json. Clouds that carry true normals (the room does) are
also scored: the sign-free angle error and the agreement of the classes with those of the
true normals. Writes ``normals.png`` (estimated ``|n|`` as RGB | classes: horizontal blue,
vertical orange, other grey | points in their own colours), ``table.md`` and metrics.json
(count, bounds, centroid, class fractions, errors).
"""

from __future__ import annotations

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.normals import estimate_normals
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.surface_orientation import (CLASS_NAMES, classify_by_cosine, classify_orientation,
                                                  point_statistics, unsigned_angle_deg)
from l3d_app.registry import DATASETS, RENDERERS, TASKS
from l3d_app.runtime.config_values import config_floats
from l3d_app.runtime.media import save_png
from l3d_app.tasks.common import require_positive

CLASS_COLOURS = torch.tensor([[0.20, 0.40, 0.90], [0.95, 0.55, 0.10], [0.60, 0.60, 0.60]])


@TASKS.register("pca_normals")
def pca_normals(cfg, ctx) -> dict:
    """Estimate, classify, score (when true normals exist), draw; return the statistics."""
    require_positive(cfg, "k", "tolerance_deg", "image_size")
    view_at = config_floats(cfg.view.at, "view.at", 3)
    if int(cfg.k) < 3 or not float(cfg.tolerance_deg) < 45:
        raise UserError(f"need k >= 3 and tolerance_deg < 45, got k={cfg.k}, tolerance_deg={cfg.tolerance_deg}")
    if not (len(cfg.up) == 3 and any(float(v) != 0 for v in cfg.up)):
        raise UserError(f"up must be a non-zero [x, y, z] direction, got {list(cfg.up)}")
    preset = str(cfg.get("preset", "scene"))
    if preset not in ("scene", "exercise"):
        raise UserError(f"preset must be scene or exercise, got {preset!r}")
    if preset == "exercise":
        above, below = float(cfg.exercise.horizontal_above), float(cfg.exercise.vertical_below)
        classify = lambda n: classify_by_cosine(n, list(cfg.up), above, below)     # noqa: E731
        classify(torch.zeros(0, 3))                                                 # bad thresholds fail here
        rule = f"|n . up| > {above:g} horizontal, < {below:g} vertical"
    else:
        classify = lambda n: classify_orientation(n, list(cfg.up), float(cfg.tolerance_deg))  # noqa: E731
        rule = f"within {float(cfg.tolerance_deg):g} degrees"
    cloud = DATASETS.build(cfg.data, device=ctx.device)
    if not isinstance(cloud, PointCloud):
        raise UserError("pca_normals needs a point-cloud data source (data=room, data=rgbd, data=*_parametric, ...)")
    points = cloud.points.float()
    with ctx.stopwatch.stage("normals"):
        normals = estimate_normals(points, k=int(cfg.k))
    classes = classify(normals)
    stats = point_statistics(points)
    counts = torch.bincount(classes.cpu(), minlength=3)
    metrics = {**{k: (v if k == "count" else [round(x, 5) for x in v]) for k, v in stats.items()},
               "k": int(cfg.k), "tolerance_deg": float(cfg.tolerance_deg),
               **{f"fraction_{n}": round(float(c) / max(1, stats["count"]), 5) for n, c in zip(CLASS_NAMES, counts)},
               **{f"count_{n}": int(c) for n, c in zip(CLASS_NAMES, counts)}, "preset": preset,
               "normals_seconds": round(ctx.stopwatch.stages["normals"], 4)}
    if cloud.normals is not None:
        err = unsigned_angle_deg(normals, cloud.normals.float())
        truth = classify(cloud.normals.float())
        metrics.update(angle_error_median_deg=round(float(err.median()), 4),
                       angle_error_mean_deg=round(float(err.mean()), 4),
                       within_10deg=round(float((err < 10).float().mean()), 5),
                       class_accuracy=round(float((truth == classes).float().mean()), 5),
                       **{f"true_fraction_{n}": round(float(c) / stats["count"], 5)
                          for n, c in zip(CLASS_NAMES, torch.bincount(truth.cpu(), minlength=3))})
    cams = look_at_cameras(float(cfg.view.distance), float(cfg.view.elevation), float(cfg.view.azimuth),
                           float(cfg.view.fov), int(cfg.image_size), at=view_at, device=ctx.device)
    renderer = RENDERERS.build(cfg.point_renderer)
    panels = [normals.abs(), CLASS_COLOURS.to(points.device)[classes]]
    if cloud.colors is not None:
        panels.append(cloud.colors.float())
    with torch.no_grad():
        images = [renderer(PointCloud(points, c), cams)["image"][0].cpu() for c in panels]
    strip = torch.cat(images, dim=1)
    save_png(ctx.path("normals.png"), strip)
    ctx.logger.image("pca_normals/normals_classes_colours", strip, 0)
    rows = "| statistic | value |\n|---|---|\n" + "".join(f"| {k} | {v} |\n" for k, v in metrics.items())
    ctx.path("table.md").write_text(rows)
    print(f"pca_normals ({rule}, k={int(cfg.k)}): " + ", ".join(f"{n} {int(c)}" for n, c in zip(CLASS_NAMES, counts))
          + f" of {stats['count']} points", flush=True)
    return metrics
