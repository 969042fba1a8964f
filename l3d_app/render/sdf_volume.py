"""Volume rendering of an SDF field (VolSDF or NeuS) with samples placed near the surface.

Per ray (unit directions, ``t`` in world units), inside the scene box from
:func:`~l3d_app.render.samplers.ray_aabb`:

1. **Coarse, SDF only, no grad**: ``n_coarse`` stratified samples of ``coarse_fn`` (the field's
   SDF, or -- much cheaper -- its trilinear :class:`SDFGridCache`, refreshed every few steps);
   the SDF there gives compositing weights (with VolSDF's ``beta`` widened to at least half
   the coarse spacing, so a thin surface between two coarse samples is still seen; NeuS's
   segment opacity already sees a sign change between samples at any ``s``).
2. **Fine, near the surface**: ``n_fine`` samples drawn from those weights
   (:func:`~l3d_app.render.samplers.sample_pdf`, ``padding`` keeps a little mass everywhere),
   evaluated with grad by the field: SDF, colour (and, when the field gives it, the SDF
   gradient for normals / the eikonal loss). Only these carry the loss.
3. **Compositing** of the fine samples (:func:`~l3d_app.render.volume.composite`, log-space
   transmittance) with segment optical depths

   - ``volsdf``: ``tau_i = alpha * Psi_beta(-f_i) * (t_{i+1} - t_i)`` (last segment ends at ``far``),
   - ``neus``:   ``tau_i = max(log Phi_s(f_i) - log Phi_s(f_{i+1}), 0)`` (last segment: 0).

``samples_per_ray`` reports both passes: coarse SDF-only evaluations (or cache look-ups) and
fine field evaluations; ``fine_samples_per_ray`` the second alone.
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.render.densities import volsdf_density
from l3d_app.render.neus import neus_optical_depth
from l3d_app.render.samplers import ray_aabb, sample_pdf, stratified_samples
from l3d_app.render.volume import Background, composite

DENSITIES = ("volsdf", "neus")

SdfFn = Callable[[torch.Tensor], torch.Tensor]
SdfColorFn = Callable[[torch.Tensor, torch.Tensor], Tuple[torch.Tensor, torch.Tensor]]


def segment_optical_depth(sdf: torch.Tensor, t: torch.Tensor, far: torch.Tensor, density: str,
                          alpha: float, beta: float, s: float) -> torch.Tensor:
    """(R, S) optical depth of the segment starting at each sample.

    Args:
        sdf: (R, S) SDF at the samples (world units); t: (R, S) sorted distances; far: (R,).
        density: ``volsdf`` (alpha: density inside, 1/units; beta: Laplace scale, units) or
            ``neus`` (s: inverse logistic scale, 1/units).
    """
    if density == "volsdf":
        deltas = torch.cat([t[:, 1:] - t[:, :-1], (far[:, None] - t[:, -1:]).clamp_min(0.0)], dim=-1)
        return volsdf_density(sdf, alpha, beta) * deltas
    if density == "neus":
        tau = neus_optical_depth(sdf[:, :-1], sdf[:, 1:], s)
        return torch.cat([tau, torch.zeros_like(tau[:, :1])], dim=-1)
    raise UserError(f"unknown SDF density '{density}'. Known: {', '.join(DENSITIES)}")


class SDFGridCache(torch.nn.Module):
    """A trilinear ``R^3`` copy of an SDF over a box: a cheap stand-in for the coarse pass.

    ``update(sdf_fn)`` evaluates the SDF (no grad) at the ``R^3`` vertices of
    :func:`~l3d_app.geometry.marching_cubes.grid_points` over ``box``; ``cache(points (..., 3))``
    interpolates them trilinearly (``grid_sample``, ``align_corners=True``; points outside the
    box take the nearest border value). A look-up costs a few ns where a field evaluation
    costs microseconds, so the coarse pass can afford many samples per ray. The values are
    as stale as the last update (the task refreshes it every ``every`` steps); they only
    place samples, the rendered SDF is always the field's own.
    """

    def __init__(self, box: Tuple[Sequence[float], Sequence[float]], resolution: int = 64):
        super().__init__()
        if int(resolution) < 2:
            raise UserError(f"SDF cache resolution must be >= 2, got {resolution}")
        self.resolution = int(resolution)
        self.register_buffer("lo", torch.as_tensor(box[0], dtype=torch.float32).reshape(3))
        self.register_buffer("hi", torch.as_tensor(box[1], dtype=torch.float32).reshape(3))
        self.register_buffer("values", torch.zeros(self.resolution, self.resolution, self.resolution))

    @torch.no_grad()
    def update(self, sdf_fn: SdfFn, chunk_size: int = 1 << 16) -> None:
        from l3d_app.geometry.marching_cubes import evaluate_grid

        self.values.copy_(evaluate_grid(sdf_fn, self.lo.tolist(), self.hi.tolist(), self.resolution,
                                        chunk_size=chunk_size, device=self.values.device))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """points (..., 3) world -> (...) interpolated SDF."""
        u = (points.reshape(-1, 3) - self.lo) / (self.hi - self.lo) * 2.0 - 1.0     # [-1, 1] per axis
        # grid_sample's (x, y, z) index (W, H, D) = values[D=i, H=j, W=k]: reverse the axes
        g = u.flip(-1).reshape(1, -1, 1, 1, 3).to(self.values.dtype)
        out = torch.nn.functional.grid_sample(self.values[None, None], g, mode="bilinear",
                                              padding_mode="border", align_corners=True)
        return out.reshape(points.shape[:-1]).to(points.dtype)


def render_sdf_rays(sdf_fn: SdfFn, sdf_color_fn: SdfColorFn, origins: torch.Tensor, dirs: torch.Tensor,
                    scene_box: Tuple[Sequence[float], Sequence[float]], density: str = "volsdf",
                    alpha: float = 10.0, beta: float = 0.05, s: float = 64.0, n_coarse: int = 64,
                    n_fine: int = 32, perturb: bool = False, generator: Optional[torch.Generator] = None,
                    background: Background = None, padding: float = 1e-3,
                    coarse_fn: Optional[SdfFn] = None) -> Dict[str, torch.Tensor]:
    """Render R rays of an SDF field (see the module docstring).

    Args:
        sdf_fn: points (N, 3) -> SDF (N,) (used without grad for the coarse pass).
        sdf_color_fn: points (N, 3), dirs (N, 3) -> (SDF (N,), rgb (N, 3)) or
            (SDF, rgb, grad (N, 3)), with grad.
        origins, dirs: (R, 3), unit ``dirs``.
        scene_box: ((x0, y0, z0), (x1, y1, z1)) world box; rays that miss it get background.
        density, alpha, beta, s: see :func:`segment_optical_depth` (floats or scalar tensors,
            which may require grad, e.g. a learnable beta).
        n_coarse, n_fine: samples per ray of each pass (>= 2 each).
        perturb: jitter both passes (from ``generator``).
        background: None (black) or an RGB triple.
        coarse_fn: SDF for the coarse pass instead of ``sdf_fn`` (e.g. an :class:`SDFGridCache`).
    Returns:
        color (R, 3), depth (R,), opacity (R,), weights (R, n_fine), t (R, n_fine),
        sdf (R, n_fine) fine-sample SDF, samples_per_ray (scalar, coarse + fine evaluations
        per ray of the rays inside the box, averaged over all rays), fine_samples_per_ray, and
        grad (R, n_fine, 3) when ``sdf_color_fn`` returns gradients.
    """
    if int(n_coarse) < 2 or int(n_fine) < 2:
        raise UserError(f"n_coarse and n_fine must be >= 2, got {n_coarse}, {n_fine}")
    near, far, hit = ray_aabb(origins, dirs, scene_box[0], scene_box[1])
    n_rays = origins.shape[0]
    t_c = stratified_samples(near, far, int(n_coarse), perturb=perturb, generator=generator)
    with torch.no_grad():
        pts = origins[:, None, :] + t_c[..., None] * dirs[:, None, :]
        f_c = (coarse_fn or sdf_fn)(pts.reshape(-1, 3)).reshape(t_c.shape)
        spacing = (far - near)[:, None] / max(int(n_coarse) - 1, 1)                    # (R, 1) per ray
        beta_c = (0.5 * spacing).clamp_min(float(beta))
        alpha_c = float(alpha)
        tau_c = segment_optical_depth(f_c, t_c, far, density, alpha_c, beta_c, float(s))
        w_c = composite(torch.zeros_like(t_c)[..., None], t_c, sigmas=tau_c,
                        deltas=torch.ones_like(t_c))["weights"] * hit[:, None]
        # each coarse sample owns its segment [t_i, t_{i+1}]
        edges = torch.cat([t_c, far[:, None]], dim=-1)
        edges = torch.maximum(edges, torch.cat([edges[:, :1], edges[:, :-1]], dim=-1))   # non-decreasing
        t = sample_pdf(edges, w_c, int(n_fine), perturb=perturb, generator=generator, padding=padding)
    pts = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    res = sdf_color_fn(pts.reshape(-1, 3), dirs[:, None, :].expand_as(pts).reshape(-1, 3))
    f, rgb = res[0].reshape(t.shape), res[1].reshape(*t.shape, -1)
    tau = segment_optical_depth(f, t, far, density, alpha, beta, s) * hit[:, None]
    out = composite(rgb, t, sigmas=tau, deltas=torch.ones_like(t), background=background)
    n_hit = hit.sum().to(origins.dtype)
    if len(res) > 2:
        out["grad"] = res[2].reshape(*t.shape, 3)
    out.update(t=t, sdf=f,
               samples_per_ray=n_hit * (int(n_coarse) + int(n_fine)) / max(n_rays, 1),
               fine_samples_per_ray=n_hit * int(n_fine) / max(n_rays, 1))
    return out

