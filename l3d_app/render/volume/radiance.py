"""Render a radiance field along rays: any ``SAMPLERS`` estimator + :func:`render_rays`.

``field(points (N, 3), dirs (N, 3)) -> (sigma (N,), rgb (N, C))`` is evaluated only at the
estimator's samples (an occupancy grid drops those in empty cells: exact for a field that is
empty there, as their optical depth would be 0).
"""

from __future__ import annotations

from typing import Callable, Dict, Optional

import torch

from l3d_app.render.volume.rendering import radiance_fn, render_rays
from l3d_app.render.volume.renderer import Background

Field = Callable[[torch.Tensor, torch.Tensor], tuple]


def render_field_rays(field: Field, origins: torch.Tensor, dirs: torch.Tensor, estimator,
                      perturb: bool = False, generator: Optional[torch.Generator] = None,
                      background: Background = None, density_field: Optional[torch.nn.Module] = None
                      ) -> Dict[str, torch.Tensor]:
    """Render R rays (unit ``dirs``) of ``field`` with samples from ``estimator``.

    ``density_field`` (default ``field``): what an estimator that probes the scene (importance)
    calls ``density`` on; ``background`` also reaches the estimator (one that renders its own proposal
    network composites over it). Returns :func:`~l3d_app.render.volume.rendering.render_rays`' outputs
    (color (R, C), depth (R,), opacity (R,), per-sample weights, samples_per_ray = field
    evaluations per ray).
    """
    t0, t1, rays = estimator.sampling(origins, dirs, perturb=perturb, generator=generator, background=background,
                                      field=density_field if density_field is not None else field)
    return render_rays(t0, t1, rays, origins.shape[0], radiance_fn(field, origins, dirs), background=background)
