"""Render a radiance field along rays bounded by the scene box, with optional empty-space
skipping (an :class:`~l3d_app.render.occupancy.OccupancyGrid`) and an optional hierarchical
(importance-sampled) fine pass.

Samples: ``n_samples`` stratified distances on each ray's [near, far] from
:func:`~l3d_app.render.samplers.ray_aabb` (rays that miss the box get no samples' worth of
density: opacity 0, background colour). Segment lengths are the sample differences, the
last one ending at ``far`` (rays end at the box; nothing beyond it absorbs). With a grid,
the field is evaluated only at samples in occupied cells: those samples are compacted,
evaluated in one call and scattered back; every other sample has density 0 (and colour 0),
which is exactly what compositing would give for a field that is empty there.
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence, Tuple

import torch

from l3d_app.render.occupancy import OccupancyGrid
from l3d_app.render.samplers import importance_samples, ray_aabb, stratified_samples
from l3d_app.render.volume import Background, composite

Field = Callable[[torch.Tensor, torch.Tensor], Tuple[torch.Tensor, torch.Tensor]]


def _shade(field: Field, origins: torch.Tensor, dirs: torch.Tensor, t: torch.Tensor, far: torch.Tensor,
           hit: torch.Tensor, grid: Optional[OccupancyGrid], background: Background
           ) -> Tuple[Dict[str, torch.Tensor], torch.Tensor]:
    """Evaluate the field at the kept samples of (R, S) distances ``t`` and composite.

    Returns composite()'s dict and the (R, S) bool mask of evaluated samples.
    """
    points = origins[:, None, :] + t[..., None] * dirs[:, None, :]           # (R, S, 3)
    keep = hit[:, None].expand_as(t)
    if grid is not None:
        keep = keep & grid.occupied(points.reshape(-1, 3)).reshape(t.shape)
    flat = keep.reshape(-1).nonzero().squeeze(-1)                           # compacted ids
    sig, rgb = field(points.reshape(-1, 3).index_select(0, flat),
                     dirs[:, None, :].expand_as(points).reshape(-1, 3).index_select(0, flat))
    sigmas = torch.zeros(t.numel(), dtype=sig.dtype, device=t.device).index_put((flat,), sig)
    colors = torch.zeros(t.numel(), rgb.shape[-1], dtype=rgb.dtype, device=t.device).index_put((flat,), rgb)
    deltas = torch.cat([t[:, 1:] - t[:, :-1], (far[:, None] - t[:, -1:]).clamp_min(0.0)], dim=-1)
    out = composite(colors.reshape(*t.shape, -1), t, sigmas=sigmas.reshape(t.shape), deltas=deltas,
                    background=background)
    return out, keep


def render_field_rays(field: Field, origins: torch.Tensor, dirs: torch.Tensor,
                      scene_box: Tuple[Sequence[float], Sequence[float]], n_samples: int,
                      perturb: bool = False, generator: Optional[torch.Generator] = None,
                      grid: Optional[OccupancyGrid] = None, n_fine: int = 0,
                      background: Background = None, min_t: float = 0.0) -> Dict[str, torch.Tensor]:
    """Render R rays through ``field(points (N, 3), dirs (N, 3)) -> (sigma (N,), rgb (N, 3))``.

    Args:
        origins, dirs: (R, 3); unit ``dirs`` (distances in world units).
        scene_box: ((x0, y0, z0), (x1, y1, z1)) world box bounding the samples.
        n_samples: coarse stratified samples per ray (S).
        perturb: jitter the stratified (and importance) samples, drawing from ``generator``.
        grid: occupancy grid for skipping (None: evaluate every sample inside the box).
        n_fine: > 0 adds a hierarchical pass: ``n_fine`` samples drawn from the coarse weights,
            merged with the coarse ones and re-evaluated (the output is the fine pass; the
            coarse colour is returned as ``color_coarse``).
        background: None (black) or an RGB triple / float.
    Returns:
        color (R, 3), depth (R,) (sum of w t; background contributes 0), opacity (R,),
        weights (R, S'), samples_per_ray: scalar tensor, the mean number of field evaluations
        per ray (both passes).
    """
    near, far, hit = ray_aabb(origins, dirs, scene_box[0], scene_box[1], min_t=min_t)
    t = stratified_samples(near, far, n_samples, perturb=perturb, generator=generator)
    out, keep = _shade(field, origins, dirs, t, far, hit, grid, background)
    evaluated = keep.sum()
    if n_fine > 0:
        coarse = out["color"]
        t_f = importance_samples(t, out["weights"], n_fine, perturb=perturb, generator=generator,
                                 near=near, far=far)
        out, keep_f = _shade(field, origins, dirs, t_f, far, hit, grid, background)
        out["color_coarse"] = coarse
        evaluated = evaluated + keep_f.sum()
    out["samples_per_ray"] = evaluated.to(origins.dtype) / max(origins.shape[0], 1)
    return out
