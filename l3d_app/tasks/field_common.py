"""Shared wiring of the field tasks (train_nerf, volsdf): one evaluation of a set of views."""

from __future__ import annotations

from typing import Dict, Tuple

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.metrics.image import psnr, ssim
from l3d_app.render.evaluation import RenderFn, evaluation_picture, render_views


@torch.no_grad()
def evaluate_views(render_fn: RenderFn, cameras: Cameras, images: torch.Tensor, chunk: int = 8192,
                   supersample: int = 1, max_picture_views: int = 4
                   ) -> Tuple[Dict[str, float], torch.Tensor, Dict[str, torch.Tensor]]:
    """Render ``cameras`` and score them against ``images`` (V, H, W, 3) in [0, 1].

    Returns ({"psnr": dB, "ssim": ...} over all views, the ``pred | truth | error | depth``
    picture of the first ``max_picture_views`` views, the renders).
    """
    out = render_views(render_fn, cameras, chunk, supersample)
    pred = out["color"].clamp(0, 1)
    metrics = {"psnr": float(psnr(pred, images)), "ssim": float(ssim(pred, images))}
    picture = evaluation_picture(pred, images, out.get("depth"), out.get("opacity"), max_picture_views)
    return metrics, picture, out
