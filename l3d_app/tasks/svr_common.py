"""Wiring shared by svr_train and svr_eval: data, batches, evaluation (F1 curve, pictures,
timing). The model and its file are :mod:`l3d_app.models.svr_model`, the F1 curve
:mod:`l3d_app.metrics.f1_curve`, the losses :mod:`l3d_app.losses.svr`.

Splits: svr_train's periodic evaluation reads the VALIDATION objects (``data.val``,
carved from the training objects); :func:`evaluate_and_report` reads the test objects,
once, at the end of svr_train or in svr_eval.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from l3d_app.data.svr_shapes import BOUNDS, SVRData
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.metrics.chamfer import nearest_distances
from l3d_app.metrics.f1_curve import f1_table, threshold_key
from l3d_app.models.svr_model import SVRModel
from l3d_app.registry import DATASETS
from l3d_app.render.charts import line_plot
from l3d_app.render.palette import error_colors as ramp_colors
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.random import randperm
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


def geometry_of(data: SVRData) -> Dict[str, Any]:
    """What decoders need to know about the data: voxel grid, cameras, image size."""
    return {"voxel_size": int(data.voxels.shape[-1]), "distance": data.distance, "fov": data.fov,
            "image_size": data.image_size, "bounds": [list(BOUNDS[0]), list(BOUNDS[1])]}


def make_batch(data: SVRData, objects: torch.Tensor, views: torch.Tensor, device) -> Dict[str, Any]:
    """Tensors of (object, view) pairs on ``device``: images (B, H, W, 3), points (B, P, 3),
    voxels (B, R, R, R), occ_points (B, Q, 3), occ_labels (B, Q), depth (B, S, H, W) and the
    S depth_cameras."""
    return {"images": data.images[objects, views].to(device), "points": data.points[objects].to(device),
            "voxels": data.voxels[objects].to(device), "occ_points": data.occ_points[objects].to(device),
            "occ_labels": data.occ_labels[objects].to(device), "depth": data.depth[objects].to(device),
            "depth_cameras": data.depth_cameras.to(device)}


# ------------------------------------------------------------------- evaluation
@torch.no_grad()
def predict_points(model: SVRModel, data: SVRData, objects: torch.Tensor, views: torch.Tensor, device,
                   num_points: int, generator: torch.Generator, batch_size: int = 16
                   ) -> Tuple[List[torch.Tensor], float]:
    """Predicted point sets (CPU, (P_i, 3)) of (object, view) pairs and the mean seconds per
    image of the model (encoder + decoder + meshing/sampling)."""
    was = model.training
    model.eval()
    out: List[torch.Tensor] = []
    t0 = time.perf_counter()
    for s in range(0, len(objects), batch_size):
        images = data.images[objects[s:s + batch_size], views[s:s + batch_size]].to(device)
        feature = model(images)
        for p in model.decoder.points(feature, num_points, generator):
            if p.shape[0] > num_points:  # dense clouds (pseudo): a random subset, same size for all decoders
                p = p[randperm(p.shape[0], generator, p.device)[:num_points]]
            out.append(p.float().cpu())
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = (time.perf_counter() - t0) / max(1, len(objects))
    model.train(was)
    return out, seconds


def error_colors(points: torch.Tensor, target: torch.Tensor, max_error: float) -> torch.Tensor:
    """(P, 3) colours of ``points`` by the distance to the nearest ``target`` point,
    blue (0) -> red (>= ``max_error``)."""
    d = nearest_distances(points, target, squared=False) if points.shape[0] else points.new_zeros(0)
    return ramp_colors(d, max_error)


def _label(image: torch.Tensor, text: str) -> torch.Tensor:
    """Panel with a small caption drawn by PIL (top-left)."""
    from PIL import Image, ImageDraw

    arr = (image.clamp(0, 1).numpy() * 255).astype(np.uint8)
    im = Image.fromarray(arr)
    ImageDraw.Draw(im).text((2, 1), text, fill=(0, 0, 0))
    return torch.from_numpy(np.array(im)).float() / 255.0


@torch.no_grad()
def visualise(model: SVRModel, data: SVRData, objects: torch.Tensor, views: torch.Tensor, device, cfg,
              generator: torch.Generator, out_png: Path, out_gif: Optional[Path]) -> torch.Tensor:
    """Rows of panels: input image | ground truth | prediction | prediction points coloured
    by their error. Stills from the input camera (PNG); optionally a turntable GIF."""
    from l3d_app.render.mesh.renderer import MeshRenderer
    from l3d_app.render.points.renderer import PointRenderer

    size, n_frames = int(cfg.turntable_size), int(cfg.num_frames)
    mesh_r = MeshRenderer(shading="lambert", background=(1.0, 1.0, 1.0), light_direction=(0.4, 1.0, 0.7))
    point_r = PointRenderer(radius=float(cfg.vis_point_radius), background=(1.0, 1.0, 1.0))
    was = model.training
    model.eval()
    feature = model(data.images[objects, views].to(device))
    shapes = model.decoder.shapes(feature)
    points = model.decoder.points(feature, int(cfg.vis_points), generator)
    model.train(was)

    def draw(shape, cams):
        if shape is None or (isinstance(shape, PointCloud) and shape.num_points == 0):
            return torch.ones(len(cams), size, size, 3)
        shape = shape.to("cpu")
        r = point_r if isinstance(shape, PointCloud) else mesh_r
        return r(shape, cams)["image"].float().cpu()

    rows, gif_rows = [], []
    for k, (o, v) in enumerate(zip(objects.tolist(), views.tolist())):
        still = look_at_cameras(data.distance, data.elevation[o, v], data.azimuth[o, v], data.fov, size)
        gt = data.mesh(o)
        pts = points[k].float().cpu()
        err = PointCloud(pts, error_colors(pts, data.points[o], float(cfg.error_max))) if len(pts) else None
        inp = torch.nn.functional.interpolate(data.images[o, v].permute(2, 0, 1)[None], size=(size, size),
                                              mode="nearest")[0].permute(1, 2, 0)
        panels = [_label(inp, "input"), _label(draw(gt, still)[0], "truth"),
                  _label(draw(shapes[k], still)[0], "prediction"), _label(draw(err, still)[0], "error")]
        rows.append(torch.cat(panels, dim=1))
        if out_gif is not None:
            turn = look_at_cameras(data.distance, float(data.elevation[o, v]),
                                   float(data.azimuth[o, v]) + torch.arange(n_frames) * (360.0 / n_frames),
                                   data.fov, size)
            gif_rows.append(torch.cat([draw(gt, turn), draw(shapes[k], turn), draw(err, turn)], dim=2))
    grid = torch.cat(rows, dim=0)
    save_png(out_png, grid)
    if out_gif is not None and gif_rows:
        save_gif(out_gif, torch.cat(gif_rows, dim=1), fps=float(cfg.fps))
    return grid


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
            grid = visualise(model, data, objects[pick], views[pick], ctx.device, cfg, gen, ctx.path("predictions.png"),
                             ctx.path("predictions.gif") if cfg.get("vis_gif", True) else None)
            images["predictions"] = grid
    f1_at = {threshold_key(t): round(float(f), 5) for t, f in zip(thresholds, table["f1"])}
    f1_05 = float(np.interp(0.05, thresholds, table["f1"])) if threshold_key(0.05) not in f1_at else f1_at["f1@0.05"]
    figures = {"f1": round(f1_05, 5), "f1@0.05": round(f1_05, 5), **f1_at, "chamfer": table["chamfer"]}
    log_test(ctx, {k: v for k, v in figures.items() if v is not None}, step, images)
    return {**figures, "empty_predictions": table["empty"], "test_objects": int(len(objects)),
            "ms_per_image": round(per_image * 1000, 3),
            "eval_seconds": round(ctx.stopwatch.stages["evaluate"], 4)}
