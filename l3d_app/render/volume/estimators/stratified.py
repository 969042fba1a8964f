"""Stratified samples on each ray's interval (NeRF's sampler; the course's box renderer)."""

from __future__ import annotations

from typing import Optional

import torch

from l3d_app.errors import UserError
from l3d_app.registry import SAMPLERS
from l3d_app.render.volume.estimators.base import Box, Estimator, Samples, segment_ends
from l3d_app.render.volume.rendering import pack_samples
from l3d_app.render.volume.samplers import stratified_samples


@SAMPLERS.register("stratified")
class StratifiedEstimator(Estimator):
    """``n_samples`` stratified distances per ray on [near, far] (see
    :func:`~l3d_app.render.volume.samplers.stratified_samples`: linspace without ``perturb``, one
    uniform draw per bin with it). Segment ``i`` ends at sample ``i + 1``, the last at ``far``.
    Rays that miss the scene box get no samples.

    Args:
        n_samples: samples per ray (S >= 1).
        scene_box: ((x0, y0, z0), (x1, y1, z1)) bounding the samples, or None to use ...
        near, far: ... a fixed interval for every ray (world units along unit rays).
    """

    def __init__(self, n_samples: int = 64, scene_box: Optional[Box] = None, near: Optional[float] = None,
                 far: Optional[float] = None, min_t: float = 0.0):
        super().__init__(scene_box, near, far, min_t)
        if int(n_samples) < 1:
            raise UserError(f"n_samples must be >= 1, got {n_samples}")
        self.n_samples = int(n_samples)

    def dense(self, origins: torch.Tensor, dirs: torch.Tensor, perturb: bool = False,
              generator: Optional[torch.Generator] = None):
        """(R, S) starts, (R, S) ends and (R,) hit flags (every ray gets its S draws, so the
        generator advances by the same amount whichever rays hit)."""
        near, far, hit = self.bounds(origins, dirs)
        t = stratified_samples(near, far, self.n_samples, perturb=perturb, generator=generator)
        return t, segment_ends(t, far), hit

    def sampling(self, origins: torch.Tensor, dirs: torch.Tensor, *, perturb: bool = False,
                 generator: Optional[torch.Generator] = None, **field_kw) -> Samples:
        t, t_end, hit = self.dense(origins, dirs, perturb, generator)
        return pack_samples(t, t_end, hit[:, None].expand_as(t))
