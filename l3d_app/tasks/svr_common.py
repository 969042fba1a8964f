"""Config glue shared by svr_train and svr_eval: data, knob checks, the test evaluation (F1 curve,
pictures, timing). Batches, predictions and pictures are :mod:`l3d_app.pipelines.svr`.

Splits: svr_train's periodic evaluation reads the VALIDATION objects (``data.val``,
carved from the training objects); :func:`evaluate_and_report` reads the test objects,
once, at the end of svr_train or in svr_eval.
"""

from __future__ import annotations

from typing import Any, Dict

import numpy as np
import torch

from l3d_app.data.svr_shapes import SVRData
from l3d_app.errors import UserError
from l3d_app.metrics.f1_curve import f1_table, threshold_key
from l3d_app.models.svr_model import SVRModel
from l3d_app.pipelines.svr import predict_points, visualise
from l3d_app.registry import DATASETS
from l3d_app.render.charts import line_plot
from l3d_app.runtime.media import save_png
from l3d_app.runtime.training import log_test

EVAL_SEED_OFFSET = 1234  # the evaluation stream: seed + this (any fixed value; chosen once)


def plain(cfg) -> Dict[str, Any]:
    """A config node as a plain dict (OmegaConf or dict)."""
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return OmegaConf.to_container(cfg, resolve=True)
    except ImportError:
        pass
    return dict(cfg)


def require_thresholds(cfg) -> None:
    """UserError unless ``cfg.thresholds`` (F1 distances, world units) is a non-empty list of
    positive numbers: checked before training, since they are read after it."""
    try:
        values = [float(t) for t in cfg.thresholds]
    except (TypeError, ValueError) as err:
        raise UserError(f"thresholds must be a list of positive numbers, got {cfg.get('thresholds')!r}") from err
    if not values or not all(t > 0 for t in values):
        raise UserError(f"thresholds must be a non-empty list of positive numbers, got {cfg.get('thresholds')!r}")


def require_eval_view(cfg, data: SVRData) -> None:
    """UserError unless ``cfg.eval_view`` indexes one of the data's views per object (checked
    when the data is loaded, before training)."""
    views = int(data.images.shape[1])
    if not 0 <= int(cfg.eval_view) < views:
        raise UserError(f"eval_view must be in [0, {views}) (the views per object), got {cfg.eval_view}")


def load_data(data_cfg) -> SVRData:
    """The configured image-to-3D data source (train / val / test object indices)."""
    data = DATASETS.build(data_cfg)
    if not isinstance(data, SVRData):
        raise UserError("svr tasks need an image-to-3D data source (data=svr_shapes)")
    return data


# ------------------------------------------------------------------- evaluation
def test_objects(cfg, data: SVRData) -> int:
    """How many test objects :func:`evaluate_and_report` predicts (``eval_objects``; 0: all)."""
    return len(data.test[: int(cfg.eval_objects)] if int(cfg.eval_objects) > 0 else data.test)


def evaluate_and_report(model: SVRModel, data: SVRData, cfg, ctx, name: str, step: int = 0) -> Dict[str, Any]:
    """The once-only evaluation on the TEST split (view ``eval_view`` of every test object):
    F1 at ``thresholds`` (curve PNG), chamfer, seconds per image, pictures, all logged as
    ``test/...`` at ``step``. Returns metrics."""
    objects = data.test[: int(cfg.eval_objects)] if int(cfg.eval_objects) > 0 else data.test
    views = torch.full_like(objects, int(cfg.eval_view))
    # a fixed evaluation stream (CPU), so svr_train's final figures and svr_eval's agree
    gen = torch.Generator().manual_seed(int(cfg.seed) + EVAL_SEED_OFFSET)
    thresholds = [float(t) for t in cfg.thresholds]
    with ctx.stopwatch.stage("evaluate"):
        preds, per_image = predict_points(model, data, objects, views, ctx.device, int(cfg.eval_points), gen)
        table = f1_table(preds, [data.points[o] for o in objects.tolist()], thresholds)
    curve = line_plot(thresholds, table["f1"], "threshold (world units; objects fit the unit sphere)",
                      "F1 (mean over test objects)", f"{name}: F1 vs threshold ({len(objects)} test objects)",
                      ylim=(0, 1), vline=0.05)
    save_png(ctx.path("f1_curve.png"), curve)
    for t, f in zip(thresholds, table["f1"]):
        ctx.logger.scalar("test/f1_curve", float(f), int(round(t * 1000)))  # x axis: threshold in 1e-3 units
    images = {"f1_curve": curve}
    with ctx.stopwatch.stage("visualise"):
        k = min(int(cfg.num_vis), len(objects))
        if k > 0:  # spread over the test set (it is ordered class by class)
            pick = torch.linspace(0, len(objects) - 1, k).round().long()
            grid = visualise(model, data, objects[pick], views[pick], ctx.device, gen, ctx.path("predictions.png"),
                             ctx.path("predictions.gif") if cfg.get("vis_gif", True) else None,
                             int(cfg.turntable_size), int(cfg.num_frames), float(cfg.vis_point_radius),
                             int(cfg.vis_points), float(cfg.error_max), float(cfg.fps))
            images["predictions"] = grid
    f1_at = {threshold_key(t): round(float(f), 5) for t, f in zip(thresholds, table["f1"])}
    f1_05 = float(np.interp(0.05, thresholds, table["f1"])) if threshold_key(0.05) not in f1_at else f1_at["f1@0.05"]
    figures = {"f1": round(f1_05, 5), "f1@0.05": round(f1_05, 5), **f1_at, "chamfer": table["chamfer"]}
    log_test(ctx, {k: v for k, v in figures.items() if v is not None}, step, images)
    return {**figures, "empty_predictions": table["empty"], "test_objects": int(len(objects)),
            "ms_per_image": round(per_image * 1000, 3),
            "eval_seconds": round(ctx.stopwatch.stages["evaluate"], 4)}
