"""Evaluation views of a field: render them, score them (PSNR, SSIM), keep the pictures.

:func:`evaluate_views` renders a set of cameras through any ``render_fn(origins, dirs)`` and scores
them against the images; :class:`BeforeAfter` keeps the validation picture before training and at
the last evaluation and writes them side by side.
"""

from __future__ import annotations

from typing import Dict, Tuple

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.metrics.image import psnr, ssim
from l3d_app.render.evaluation import RenderFn, evaluation_picture, render_views
from l3d_app.runtime.media import save_png


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


class BeforeAfter:
    """The validation picture before training and at the last evaluation, side by side.

    ``before(ctx, evaluate_fn)`` renders the val views once before the first step (no sampler
    update, no random draw: the run's stream is untouched) and logs ``val/before_training``;
    ``after(picture)`` keeps each evaluation's picture; ``save(ctx)`` writes ``before_after.png``
    (before above, last evaluation below) and returns ``{"before_val_psnr"}``. A task checkpoints
    it with the run (``Trainable.extra``), so a resumed run keeps both.
    """

    def __init__(self):
        self.pictures: Dict[str, torch.Tensor] = {}
        self.before_psnr = float("nan")

    def before(self, ctx, evaluate_fn) -> None:
        with torch.no_grad():
            metrics, self.pictures["before"], _ = evaluate_fn()
        self.before_psnr = float(metrics["psnr"])
        ctx.logger.image("val/before_training", self.pictures["before"], 0)

    def after(self, picture: torch.Tensor) -> None:
        self.pictures["last"] = picture

    def state_dict(self) -> Dict[str, object]:
        return {"pictures": dict(self.pictures), "before_psnr": self.before_psnr}

    def load_state_dict(self, state: Dict[str, object]) -> None:
        self.pictures = dict(state["pictures"])
        self.before_psnr = float(state["before_psnr"])

    def save(self, ctx) -> Dict[str, float]:
        if {"before", "last"} <= set(self.pictures):
            save_png(ctx.path("before_after.png"), torch.cat([self.pictures["before"], self.pictures["last"]], 0))
            return {"before_val_psnr": round(self.before_psnr, 4)}
        return {}
