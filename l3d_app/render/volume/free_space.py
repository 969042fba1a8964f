"""Known free space along training rays, read off a radiance field fitted to the same images.

A radiance field is not bound to one surface: where the images show the far side of a gap, it
puts its density there, and the stretch of each training ray before the density starts is empty.
:func:`opacity_distance` finds, per ray, where the accumulated opacity first reaches a level;
:func:`free_distances` does so for many rays of a trained field; :class:`FreeRays` keeps each
ray's free segment (box entry to that distance less a margin) and draws points on them, at which a
surface model can be told "empty" (the loss terms of :mod:`~l3d_app.losses.free_space`).
Nothing is said about what no ray passes through (hidden interiors, the unseen underside).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch

from l3d_app.render.volume.rendering import radiance_fn, render_rays
from l3d_app.render.volume.samplers import ray_aabb
from l3d_app.runtime.random import rand, randint


def opacity_distance(t_starts: torch.Tensor, transmittance: torch.Tensor, alphas: torch.Tensor,
                     ray_indices: torch.Tensor, n_rays: int, level: float) -> torch.Tensor:
    """Per ray, the start of the first sample after which the accumulated opacity is >= ``level``.

    Args:
        t_starts, transmittance, alphas, ray_indices: (N,) packed samples as
            :func:`~l3d_app.render.volume.rendering.render_rays` returns them (``transmittance`` = light
            reaching the sample, ``alphas`` = its opacity).
        n_rays: R. level: in (0, 1].
    Returns:
        (R,) distance along the ray (the units of ``t_starts``); +inf where the level is never reached.
    """
    after = 1.0 - transmittance * (1.0 - alphas)          # opacity accumulated through each sample
    t = torch.where(after >= level, t_starts, torch.full_like(t_starts, float("inf")))
    out = torch.full((n_rays,), float("inf"), dtype=t_starts.dtype, device=t_starts.device)
    return out.scatter_reduce(0, ray_indices, t, "amin")


@torch.no_grad()
def free_distances(field, estimator, origins: torch.Tensor, dirs: torch.Tensor, level: float,
                   chunk: int = 16384) -> torch.Tensor:
    """(R,) :func:`opacity_distance` at opacity ``level`` in (0, 1] of R rays (``origins``, unit ``dirs``
    (R, 3)) through a radiance ``field(points, dirs) -> (sigma, rgb)`` sampled by ``estimator`` (no jitter),
    ``chunk`` rays per render."""
    out = []
    for s in range(0, origins.shape[0], chunk):
        o, d = origins[s:s + chunk], dirs[s:s + chunk]
        t0, t1, idx = estimator.sampling(o, d, perturb=False, field=field)
        r = render_rays(t0, t1, idx, o.shape[0], radiance_fn(field, o, d))
        out.append(opacity_distance(t0, r["transmittance"], r["alphas"], idx, o.shape[0], float(level)))
    return torch.cat(out) if out else origins.new_zeros(0)


@dataclass
class FreeRays:
    """Training rays with a known free segment ``[near, far]`` (world units along unit ``dirs``).

    ``origins``, ``dirs`` (M, 3); ``near``, ``far`` (M,), ``far > near``; ``index`` (M,) each ray's
    index among the rays it was read off (None: not known); ``open_end`` (M,) bool: the radiance field
    never reached the opacity level on it (free to the box exit; None: not known)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor
    index: Optional[torch.Tensor] = None
    open_end: Optional[torch.Tensor] = None

    @classmethod
    def from_distances(cls, origins: torch.Tensor, dirs: torch.Tensor, distances: torch.Tensor,
                       box: Tuple[Sequence[float], Sequence[float]], margin: float,
                       index: Optional[torch.Tensor] = None) -> "FreeRays":
        """Each ray's stretch inside ``box`` up to ``distances - margin`` (a ray that never reaches
        the opacity level is free to the box exit); rays with nothing left are dropped. ``index`` (R,):
        the rays' indices among the training rays (default ``0..R-1``), kept for :meth:`ends_per_ray`."""
        near, far, hit = ray_aabb(origins, dirs, box[0], box[1])
        end = torch.minimum(far, distances - float(margin))
        keep = hit & (end > near)
        if index is None:
            index = torch.arange(origins.shape[0], device=origins.device)
        return cls(origins[keep], dirs[keep], near[keep], end[keep], index[keep], torch.isinf(distances)[keep])

    def ends_per_ray(self, n_rays: int, covered: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(n_rays,) where each training ray's free segment ends (world units along its unit direction):
        ``far`` for the rays kept here, -inf (nothing known to be free) for the others. ``covered``
        (n_rays,) bool, e.g. the images' alpha >= 0.5: a covered ray on which the radiance field never
        became opaque gets -inf too (its transparency there contradicts the data: no claim is made)."""
        if self.index is None:
            raise ValueError("these free rays do not know their training-ray indices (built without index)")
        ends = torch.full((int(n_rays),), float("-inf"), dtype=self.far.dtype, device=self.far.device)
        far = self.far
        if covered is not None and self.open_end is not None:
            far = torch.where(covered[self.index] & self.open_end, torch.full_like(far, float("-inf")), far)
        return ends.index_put_((self.index,), far)

    def __len__(self) -> int:
        return int(self.near.shape[0])

    def sample(self, n: int, generator: Optional[torch.Generator] = None,
               shorten: float = 0.0) -> Tuple[torch.Tensor, torch.Tensor]:
        """(n, 3) points, each uniform on the free segment of a uniformly drawn ray, and (n,) the
        lengths of those segments (density x length estimates the segment's optical depth).
        ``shorten`` >= 0 (world units) first takes that much off each segment's far end; a ray
        with nothing left gives its near point and length 0."""
        dev = self.origins.device
        i = randint(0, len(self), (n,), generator, dev)
        length = (self.far[i] - float(shorten) - self.near[i]).clamp_min(0.0)
        t = self.near[i] + rand((n,), generator, dev) * length
        return self.origins[i] + t[:, None] * self.dirs[i], length
