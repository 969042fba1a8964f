"""Volume rendering of an SDF field (VolSDF or NeuS): the SDF-specific callback of
:func:`~l3d_app.render.volume.rendering.render_rays`.

Samples come from an estimator (usually :class:`~l3d_app.render.volume.estimators.SDFCacheProposal`:
a trilinear SDF cache places a few field samples at the zero level set); the field gives
SDF and colour (and, when it has one, its exact spatial gradient, for normals and the
eikonal loss) at each segment's start; a ``DENSITIES`` module
(:class:`~l3d_app.render.sdf.densities.VolSDFDensity`, :class:`~l3d_app.render.sdf.neus.NeuSDensity`)
turns the SDF of a ray's samples into segment optical depths:

- ``volsdf``: ``tau_i = alpha * Psi_beta(-f_i) * (t_end_i - t_start_i)``,
- ``neus``:   ``tau_i = max(log Phi_s(f_i) - log Phi_s(f_{i+1}), 0)`` (last segment: 0).
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import torch

from l3d_app.render.volume.rendering import points_of, render_rays
from l3d_app.render.sdf.cache import SDFGridCache  # noqa: F401  (re-exported)
from l3d_app.render.volume.renderer import Background

SdfColorFn = Callable[[torch.Tensor, torch.Tensor], Tuple[torch.Tensor, ...]]


def sdf_rgb_sigma_fn(sdf_color_fn: SdfColorFn, origins: torch.Tensor, dirs: torch.Tensor, density
                     ) -> Callable:
    """``rgb_sigma_fn`` for :func:`render_rays`: ``sdf_color_fn(points (N, 3), dirs (N, 3)) ->
    (sdf (N,), rgb (N, C)[, grad (N, 3)])`` at the segment starts, optical depth by ``density``.
    The SDF (and the gradient) come back in ``aux``."""

    def fn(t_starts, t_ends, ray_indices):
        pts, d = points_of(origins, dirs, t_starts, ray_indices)
        res = sdf_color_fn(pts, d)
        out = {"rgb": res[1], "tau": density.optical_depth(res[0], t_starts, t_ends, ray_indices), "sdf": res[0]}
        if len(res) > 2:
            out["grad"] = res[2]
        return out
    return fn


def render_sdf_rays(sdf_color_fn: SdfColorFn, origins: torch.Tensor, dirs: torch.Tensor, estimator, density,
                    field: Optional[torch.nn.Module] = None, perturb: bool = False,
                    generator: Optional[torch.Generator] = None, background: Background = None
                    ) -> Dict[str, torch.Tensor]:
    """Render R rays of an SDF field: ``estimator.sampling`` then :func:`render_rays`.

    Args:
        sdf_color_fn: see :func:`sdf_rgb_sigma_fn` (with grad while training).
        origins, dirs: (R, 3), unit ``dirs``.
        estimator: a ``SAMPLERS`` estimator (given ``field=`` and ``density=``).
        density: a ``DENSITIES`` module.
        field: the model (``field.sdf`` for estimators without a cache).
    Returns:
        :func:`render_rays`' outputs plus, per packed sample, ``t`` (N,), ``sdf`` (N,) and
        ``grad`` (N, 3) when the field gives it, and the estimator's figures
        (``samples_per_ray`` counting coarse look-ups, ``fine_samples_per_ray``).
    """
    t0, t1, rays = estimator.sampling(origins, dirs, perturb=perturb, generator=generator, field=field,
                                      density=density)
    out = render_rays(t0, t1, rays, origins.shape[0], sdf_rgb_sigma_fn(sdf_color_fn, origins, dirs, density),
                      background=background)
    aux = out.pop("aux")
    out.update(t=t0, ray_indices=rays, **aux)
    for k, v in estimator.stats().items():
        out[k] = torch.tensor(float(v))
    return out
