"""Single-view reconstruction (svr_train, svr_eval): batches, predicted point sets, pictures.

The model and its file are :mod:`l3d_app.models.svr_model`, the F1 curve
:mod:`l3d_app.metrics.f1_curve`, the losses :mod:`l3d_app.losses.svr`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from l3d_app.data.svr_shapes import BOUNDS, SVRData
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.metrics.chamfer import nearest_distances
from l3d_app.models.svr_model import SVRModel
from l3d_app.render.palette import error_colors as ramp_colors
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.random import randperm


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
def visualise(model: SVRModel, data: SVRData, objects: torch.Tensor, views: torch.Tensor, device,
              generator: torch.Generator, out_png: Path, out_gif: Optional[Path], size: int = 128, n_frames: int = 24,
              point_radius: float = 1.0, n_points: int = 2000, error_max: float = 0.1, fps: float = 12.0
              ) -> torch.Tensor:
    """Rows of panels (``size`` px each): input image | ground truth | prediction | ``n_points`` predicted
    points coloured by their error (blue 0 -> red ``error_max``, world units; ``point_radius`` px).
    Stills from the input camera (PNG); optionally a turntable GIF of ``n_frames`` frames at ``fps``."""
    from l3d_app.render.mesh.renderer import MeshRenderer
    from l3d_app.render.points.renderer import PointRenderer

    size, n_frames = int(size), int(n_frames)
    mesh_r = MeshRenderer(shading="lambert", background=(1.0, 1.0, 1.0), light_direction=(0.4, 1.0, 0.7))
    point_r = PointRenderer(radius=float(point_radius), background=(1.0, 1.0, 1.0))
    was = model.training
    model.eval()
    feature = model(data.images[objects, views].to(device))
    shapes = model.decoder.shapes(feature)
    points = model.decoder.points(feature, int(n_points), generator)
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
        err = PointCloud(pts, error_colors(pts, data.points[o], float(error_max))) if len(pts) else None
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
        save_gif(out_gif, torch.cat(gif_rows, dim=1), fps=float(fps))
    return grid
