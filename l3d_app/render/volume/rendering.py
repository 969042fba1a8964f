"""One volume-rendering function for packed ray samples (nerfacc's ``rendering()`` split).

An estimator (:mod:`l3d_app.render.volume.estimators`, registry ``SAMPLERS``) decides WHERE to
sample and returns packed segments::

    t_starts (N,), t_ends (N,)   segment [t_start, t_end) along ray ``ray_indices`` (world
                                 units along unit directions)
    ray_indices (N,) long        which of the R rays each segment belongs to; segments of a
                                 ray are contiguous and sorted front to back

:func:`render_rays` then asks ``rgb_sigma_fn(t_starts, t_ends, ray_indices)`` WHAT is there
and composites (emission-absorption, see :mod:`l3d_app.render.volume.renderer` for the maths). The
callback returns either a tuple ``(rgb (N, C), sigma (N,))`` (density in 1 / world units;
optical depth ``sigma * (t_end - t_start)``) or a dict with ``"rgb"`` and exactly one of
``"sigma"``, ``"alpha"`` (opacity in [0, 1], e.g. the course's box rule) or ``"tau"`` (the
segment's optical depth itself, e.g. NeuS, whose opacity needs both segment ends); any
other (N, ...) entries of the dict are returned unchanged under ``"aux"``.

Compositing scatters the packed values into a dense (R, S_max) layout (S_max = most samples
of any ray, the rest padded with zero optical depth) and uses
:func:`~l3d_app.render.volume.renderer.composite`: log-space transmittance, exact for huge
``sigma * delta``. Padding adds exact zeros, so a ray's result does not depend on the others.
"""

from __future__ import annotations

import math
from typing import Callable, Dict, Optional, Tuple, Union

import torch

from l3d_app.render.volume.renderer import Background, composite

RgbSigmaFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor],
                      Union[Tuple[torch.Tensor, torch.Tensor], Dict[str, torch.Tensor]]]


def pack_samples(t: torch.Tensor, t_ends: torch.Tensor, keep: torch.Tensor
                 ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Dense (R, S) starts / ends and a bool mask -> packed (t_starts, t_ends, ray_indices),
    in row-major order (each ray's kept samples contiguous, front to back)."""
    if bool(keep.all()):     # every sample kept: a reshape, no gather
        rays = torch.arange(t.shape[0], device=t.device).repeat_interleave(t.shape[1])
        return t.reshape(-1), t_ends.reshape(-1), rays
    rows, _ = keep.nonzero(as_tuple=True)
    return t[keep], t_ends[keep], rows


def dense_layout(ray_indices: torch.Tensor, n_rays: int) -> Tuple[torch.Tensor, int]:
    """(N,) position of each packed sample inside its ray and S_max (samples of the fullest ray)."""
    counts = torch.bincount(ray_indices, minlength=n_rays)
    if ray_indices.numel() == 0:
        return ray_indices.clone(), 0
    first = torch.cumsum(counts, 0) - counts
    pos = torch.arange(ray_indices.numel(), device=ray_indices.device) - first[ray_indices]
    return pos, int(counts.max())


def _scatter(values: torch.Tensor, ray_indices: torch.Tensor, pos: Optional[torch.Tensor], n_rays: int,
             s_max: int) -> torch.Tensor:
    if pos is None:          # every ray has s_max samples: the packed order is the dense one
        return values.reshape(n_rays, s_max, *values.shape[1:])
    out = values.new_zeros((n_rays, s_max, *values.shape[1:]))
    out[ray_indices, pos] = values
    return out


def render_rays(t_starts: torch.Tensor, t_ends: torch.Tensor, ray_indices: torch.Tensor, n_rays: int,
                rgb_sigma_fn: RgbSigmaFn, background: Background = None) -> Dict[str, torch.Tensor]:
    """Composite R rays from packed samples (see the module docstring).

    Args:
        t_starts, t_ends: (N,) segment ends (world units); ray_indices: (N,) long, sorted.
        n_rays: R (rays with no sample get opacity 0 and the background).
        rgb_sigma_fn: ``(t_starts, t_ends, ray_indices) -> (rgb, sigma)`` or a dict (above).
        background: None (black), a float, a (C,) colour or (R, C) colours.
    Returns:
        color (R, C), depth (R,) = sum_i w_i t_start_i (not divided by opacity), opacity (R,),
        and per sample (N,): weights, transmittance, alphas, plus ``aux`` (the callback's
        extra outputs) and ``samples_per_ray`` (scalar tensor, N / R).
    """
    res = rgb_sigma_fn(t_starts, t_ends, ray_indices)
    if isinstance(res, dict):
        res = dict(res)
        rgb = res.pop("rgb")
        kinds = [k for k in ("sigma", "alpha", "tau") if k in res]
        if len(kinds) != 1:
            raise ValueError(f"rgb_sigma_fn must return exactly one of sigma / alpha / tau, got {sorted(res)}")
        kind, value = kinds[0], res.pop(kinds[0])
        aux = res
    else:
        rgb, value = res[0], res[1]
        kind, aux = "sigma", {}
    pos, s_max = dense_layout(ray_indices, n_rays)
    full = s_max * n_rays == ray_indices.numel()     # equal counts (they sum to N): no scatter needed
    if full:
        pos = None
    t_d = _scatter(t_starts, ray_indices, pos, n_rays, s_max)
    channels = math.prod(rgb.shape[1:])              # (N,) or (N, C); explicit so that N = 0 works
    rgb_d = _scatter(rgb.reshape(rgb.shape[0], channels), ray_indices, pos, n_rays, s_max)
    if kind == "alpha":
        out = composite(rgb_d, t_d, alphas=_scatter(value.reshape(-1), ray_indices, pos, n_rays, s_max),
                        background=background)
    else:
        tau = value.reshape(-1) * (t_ends - t_starts) if kind == "sigma" else value.reshape(-1)
        tau_d = _scatter(tau, ray_indices, pos, n_rays, s_max)
        out = composite(rgb_d, t_d, sigmas=tau_d, deltas=torch.ones_like(tau_d), background=background)
    per_sample = {k: (out[k].reshape(-1) if full else out[k][ray_indices, pos])
                  for k in ("weights", "transmittance", "alphas")}
    return {"color": out["color"], "depth": out["depth"], "opacity": out["opacity"],
            "optical_depth": out["optical_depth"], **per_sample,
            "aux": aux, "samples_per_ray": torch.tensor(ray_indices.numel() / max(n_rays, 1))}


def points_of(origins: torch.Tensor, dirs: torch.Tensor, t: torch.Tensor, ray_indices: torch.Tensor
              ) -> Tuple[torch.Tensor, torch.Tensor]:
    """(N, 3) points ``o + t d`` of packed samples and their (N, 3) ray directions."""
    d = dirs.index_select(0, ray_indices)
    return origins.index_select(0, ray_indices) + t[:, None] * d, d


def radiance_fn(field: Callable, origins: torch.Tensor, dirs: torch.Tensor) -> RgbSigmaFn:
    """``rgb_sigma_fn`` of a radiance field ``field(points (N, 3), dirs (N, 3)) -> (sigma (N,), rgb (N, C))``
    (samples at the segment starts)."""
    def fn(t_starts, t_ends, ray_indices):
        pts, d = points_of(origins, dirs, t_starts, ray_indices)
        sigma, rgb = field(pts, d)
        return rgb, sigma
    return fn
