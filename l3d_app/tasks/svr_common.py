"""Pieces shared by svr_train and svr_eval: the model (image encoder + decoder), batches,
the self-contained model file, and the evaluation (F1 curve, pictures, timing).

The model file ``svr_model.pt`` holds the weights and everything that rebuilds the model
(encoder and decoder configs, the data geometry) and the data config, so ``svr_eval``
evaluates on the same test split without any other knob.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import nn

from l3d_app.data.svr_shapes import SVRData
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.metrics.chamfer import nearest_distances, nearest_neighbors_both
from l3d_app.models import svr_decoders, svr_pseudo  # noqa: F401  (register the decoders)
from l3d_app.models.svr_encoder import ImageEncoder
from l3d_app.registry import DATASETS, MODELS
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.tasks.point_learning import save_best

MODEL_FILE = "svr_model.pt"


class SVRModel(nn.Module):
    """Image encoder + decoder: ``model.decoder.loss(model(images), batch)`` etc."""

    def __init__(self, encoder: ImageEncoder, decoder: nn.Module):
        super().__init__()
        self.encoder, self.decoder = encoder, decoder

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) -> (B, latent_dim) features."""
        return self.encoder(images)


def plain(cfg) -> Dict[str, Any]:
    """A config node as a plain dict (OmegaConf or dict)."""
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return OmegaConf.to_container(cfg, resolve=True)
    except ImportError:
        pass
    return dict(cfg)


def load_data(data_cfg) -> SVRData:
    data = DATASETS.build(data_cfg)
    if not isinstance(data, SVRData):
        raise UserError("svr tasks need an image-to-3D data source (data=svr_shapes)")
    return data


def geometry_of(data: SVRData) -> Dict[str, Any]:
    """What decoders need to know about the data: voxel grid, cameras, image size."""
    return {"voxel_size": int(data.voxels.shape[-1]), "distance": data.distance, "fov": data.fov,
            "image_size": data.image_size}


def build_model(encoder_cfg: Dict, decoder_cfg: Dict, geometry: Dict) -> SVRModel:
    encoder = ImageEncoder(image_size=int(geometry["image_size"]), **encoder_cfg)
    decoder = MODELS.build(decoder_cfg, latent_dim=encoder.latent_dim, geometry=geometry)
    return SVRModel(encoder, decoder)


def n_params(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def make_batch(data: SVRData, objects: torch.Tensor, views: torch.Tensor, device) -> Dict[str, Any]:
    """Tensors of (object, view) pairs on ``device``: images (B, H, W, 3), points (B, P, 3),
    voxels (B, R, R, R), occ_points (B, Q, 3), occ_labels (B, Q), depth (B, S, H, W) and the
    S depth_cameras."""
    return {"images": data.images[objects, views].to(device), "points": data.points[objects].to(device),
            "voxels": data.voxels[objects].to(device), "occ_points": data.occ_points[objects].to(device),
            "occ_labels": data.occ_labels[objects].to(device), "depth": data.depth[objects].to(device),
            "depth_cameras": data.depth_cameras.to(device)}


def save_model(path: Path, model: SVRModel, meta: Dict[str, Any]) -> None:
    """Write the self-contained model file (weights + configs, see the module docstring)."""
    save_best(path, model, meta)


def load_model(path, device) -> Tuple[SVRModel, Dict[str, Any]]:
    """Rebuild the model of a ``svr_model.pt`` (or of a run folder holding one)."""
    if path is None or str(path) == "":
        raise UserError(f"svr_eval needs checkpoint=PATH: a {MODEL_FILE} or the svr_train run folder holding it")
    p = Path(str(path)).expanduser()
    if p.is_dir():
        p = p / MODEL_FILE
    if not p.is_file():
        raise UserError(f"svr model checkpoint not found: {p} (train one with task=svr_train)")
    try:
        meta = torch.load(p, map_location="cpu", weights_only=False)
    except Exception as err:  # not a torch file, truncated, ...
        raise UserError(f"cannot read svr model checkpoint {p}: {err}") from err
    if not isinstance(meta, dict) or "decoder_cfg" not in meta:
        raise UserError(f"{p} is not an svr_train model file ({MODEL_FILE})")
    model = build_model(meta["encoder_cfg"], meta["decoder_cfg"], meta["geometry"])
    model.load_state_dict(meta.pop("state"))
    return model.to(device).eval(), meta


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
                p = p[torch.randperm(p.shape[0], generator=generator, device=generator.device)[:num_points].to(p.device)]
            out.append(p.float().cpu())
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = (time.perf_counter() - t0) / max(1, len(objects))
    model.train(was)
    return out, seconds


@torch.no_grad()
def f1_curve(pred: torch.Tensor, target: torch.Tensor, thresholds: Sequence[float]) -> Tuple[np.ndarray, float]:
    """F1 of ``pred`` (N, 3) vs ``target`` (M, 3) at every threshold from ONE nearest-neighbour
    pass (the same definition as :func:`l3d_app.metrics.fscore.fscore`, which would search
    again per threshold), and the chamfer distance (sum of mean squared nearest distances)."""
    idx_pt, idx_tp = nearest_neighbors_both(pred, target, chunk_size=int(pred.shape[0]))
    d_pt = (pred - target[idx_pt]).norm(dim=-1)
    d_tp = (target - pred[idx_tp]).norm(dim=-1)
    th = torch.tensor([float(t) for t in thresholds], dtype=d_pt.dtype)
    p = (d_pt[None] <= th[:, None]).double().mean(1)
    r = (d_tp[None] <= th[:, None]).double().mean(1)
    f1 = torch.where(p + r > 0, 2 * p * r / (p + r).clamp_min(1e-300), torch.zeros_like(p))
    return f1.numpy(), float(d_pt.square().mean() + d_tp.square().mean())


def f1_table(preds: Sequence[torch.Tensor], targets: Sequence[torch.Tensor], thresholds: Sequence[float]
             ) -> Dict[str, Any]:
    """Mean over objects of F1 at each threshold (empty predictions score 0) and the mean
    chamfer of the non-empty ones (None if all are empty).
    Returns {"f1": (T,) array, "chamfer": float or None, "empty": int}."""
    f1 = np.zeros((len(preds), len(thresholds)))
    chamfers, empty = [], 0
    for i, (p, t) in enumerate(zip(preds, targets)):
        if p.shape[0] == 0:
            empty += 1
            continue
        f1[i], ch = f1_curve(p, t, thresholds)
        chamfers.append(ch)
    return {"f1": f1.mean(0), "chamfer": float(np.mean(chamfers)) if chamfers else None, "empty": empty}


def threshold_key(t: float) -> str:
    return f"f1@{float(t):g}"


def plot_f1_curve(thresholds: Sequence[float], f1: Sequence[float], title: str, path: Path) -> np.ndarray:
    """Write the F1-vs-threshold curve as a PNG; returns it as (H, W, 3) float in [0, 1]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.6), dpi=100)
    ax.plot(list(thresholds), list(f1), "o-", color="tab:blue")
    ax.axvline(0.05, color="0.6", lw=0.8, ls="--")
    ax.set_xlabel("threshold (world units; objects fit the unit sphere)")
    ax.set_ylabel("F1 (mean over test objects)")
    ax.set_ylim(0, 1)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.float32) / 255.0
    plt.close(fig)
    save_png(path, image)
    return image


def error_colors(points: torch.Tensor, target: torch.Tensor, max_error: float) -> torch.Tensor:
    """(P, 3) colours of ``points`` by the distance to the nearest ``target`` point,
    blue (0) -> red (>= ``max_error``), matplotlib's coolwarm."""
    import matplotlib

    d = nearest_distances(points, target, squared=False) if points.shape[0] else points.new_zeros(0)
    x = (d / max_error).clamp(0, 1).numpy()
    return torch.from_numpy(matplotlib.colormaps["coolwarm"](x)[:, :3]).float()


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
    from l3d_app.render.mesh_renderer import MeshRenderer
    from l3d_app.render.points import PointRenderer

    size, n_frames = int(cfg.vis_size), int(cfg.num_frames)
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


def evaluate_and_report(model: SVRModel, data: SVRData, cfg, ctx, name: str) -> Dict[str, Any]:
    """Full evaluation on the test split (view ``eval_view`` of every test object): F1 at
    ``thresholds`` (curve PNG, logged), chamfer, seconds per image, pictures. Returns metrics."""
    objects = data.test[: int(cfg.eval_objects)] if int(cfg.eval_objects) > 0 else data.test
    views = torch.full_like(objects, int(cfg.eval_view) % data.images.shape[1])
    gen = torch.Generator(device=ctx.device).manual_seed(int(cfg.seed) + 1234)
    thresholds = [float(t) for t in cfg.thresholds]
    with ctx.stopwatch.stage("evaluate"):
        preds, per_image = predict_points(model, data, objects, views, ctx.device, int(cfg.eval_points), gen)
        table = f1_table(preds, [data.points[o] for o in objects.tolist()], thresholds)
    curve = plot_f1_curve(thresholds, table["f1"], f"{name}: F1 vs threshold ({len(objects)} test objects)",
                          ctx.path("f1_curve.png"))
    ctx.logger.image("eval/f1_curve", curve)
    for t, f in zip(thresholds, table["f1"]):
        ctx.logger.scalar("eval/f1_curve", float(f), int(round(t * 1000)))  # x axis: threshold in 1e-3 units
    with ctx.stopwatch.stage("visualise"):
        k = min(int(cfg.num_vis), len(objects))
        if k > 0:  # spread over the test set (it is ordered class by class)
            pick = torch.linspace(0, len(objects) - 1, k).round().long()
            grid = visualise(model, data, objects[pick], views[pick], ctx.device, cfg, gen, ctx.path("predictions.png"),
                             ctx.path("predictions.gif") if cfg.get("vis_gif", True) else None)
            ctx.logger.image("eval/predictions", grid)
    f1_at = {threshold_key(t): round(float(f), 5) for t, f in zip(thresholds, table["f1"])}
    f1_05 = float(np.interp(0.05, thresholds, table["f1"])) if threshold_key(0.05) not in f1_at else f1_at["f1@0.05"]
    return {"f1": round(f1_05, 5), "f1@0.05": round(f1_05, 5), **f1_at, "chamfer": table["chamfer"],
            "empty_predictions": table["empty"], "test_objects": int(len(objects)),
            "ms_per_image": round(per_image * 1000, 3),
            "eval_seconds": round(ctx.stopwatch.stages["evaluate"], 4)}
