"""Hierarchical (importance) estimator: a no-grad coarse pass of the field places the fine samples."""

from __future__ import annotations

from typing import Optional

import torch

from l3d_app.errors import UserError
from l3d_app.registry import SAMPLERS
from l3d_app.render.volume.estimators.base import Box, Samples, segment_ends
from l3d_app.render.volume.estimators.stratified import StratifiedEstimator
from l3d_app.render.volume.rendering import pack_samples
from l3d_app.render.volume.samplers import importance_samples
from l3d_app.render.volume.renderer import composite


@SAMPLERS.register("importance")
class ImportanceEstimator(StratifiedEstimator):
    """NeRF's hierarchical sampling with one network used as its own proposal.

    ``n_samples`` stratified samples are evaluated by ``field.density`` WITHOUT gradient;
    their compositing weights (plus ``padding``) are a pdf from which ``n_fine`` more samples
    are drawn (:func:`~l3d_app.render.volume.samplers.importance_samples`); the union (S + n_fine per
    ray, sorted) is returned for the rendering pass, which alone carries the loss.
    ``sampling`` needs ``field=`` (anything with ``density(points (N, 3)) -> (N,)``).
    """

    def __init__(self, scene_box: Optional[Box] = None, n_samples: int = 64, n_fine: int = 64,
                 padding: float = 1e-5, near: Optional[float] = None, far: Optional[float] = None,
                 min_t: float = 0.0):
        super().__init__(n_samples, scene_box=scene_box, near=near, far=far, min_t=min_t)
        if int(n_fine) < 1:
            raise UserError(f"n_fine must be >= 1, got {n_fine}")
        self.n_fine, self.padding = int(n_fine), float(padding)

    def sampling(self, origins: torch.Tensor, dirs: torch.Tensor, *, perturb: bool = False,
                 generator: Optional[torch.Generator] = None, field=None, **field_kw) -> Samples:
        if field is None or not hasattr(field, "density"):
            raise ValueError("the importance estimator needs field= with a density(points) method")
        near, far, hit = self.bounds(origins, dirs)
        t_c, _, _ = self.dense(origins, dirs, perturb, generator)
        with torch.no_grad():
            pts = origins[:, None, :] + t_c[..., None] * dirs[:, None, :]
            sigma = field.density(pts.reshape(-1, 3)).reshape(t_c.shape) * hit[:, None]
            w = composite(torch.zeros_like(t_c)[..., None], t_c, sigmas=sigma,
                          deltas=segment_ends(t_c, far) - t_c)["weights"]
            t = importance_samples(t_c, w, self.n_fine, perturb=perturb, generator=generator,
                                   padding=self.padding, near=near, far=far)
        return pack_samples(t, segment_ends(t, far), hit[:, None].expand_as(t))

    def stats(self) -> dict:
        """The no-grad coarse probe's samples per ray (the rendered ones are the task's ``samples_per_ray``)."""
        return {"coarse_samples_per_ray": float(self.n_samples)}
