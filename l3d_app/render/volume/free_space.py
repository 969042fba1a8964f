"""Known free space along training rays, read off a radiance field fitted to the same images.

A radiance field is not bound to one surface: where the images show the far side of a gap, it
puts its density there, and the stretch of each training ray before the density starts is empty.
:func:`opacity_distance` finds, per ray, where the accumulated opacity first reaches a level;
:func:`free_distances` does so for many rays of a trained field; :class:`FreeRays` keeps each
ray's free segment (box entry to that distance less a margin) and draws points on them, at which a
surface model can be told "empty" (:func:`~l3d_app.losses.free_space.free_stretch_loss`).
Nothing is said about what no ray passes through (hidden interiors, the unseen underside).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
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
def free_distances(field, estimator, origins: torch.Tensor, dirs: torch.Tensor, level,
                   chunk: int = 16384) -> torch.Tensor:
    """:func:`opacity_distance` of R rays (``origins``, unit ``dirs`` (R, 3)) through a radiance
    ``field(points, dirs) -> (sigma, rgb)`` sampled by ``estimator`` (no jitter).

    ``level``: one opacity level in (0, 1] -> (R,); or a sequence of K levels -> (R, K), each
    column that level's distance, all read off one render of each ray."""
    levels = [float(x) for x in level] if isinstance(level, (list, tuple)) else [float(level)]
    out = []
    for s in range(0, origins.shape[0], chunk):
        o, d = origins[s:s + chunk], dirs[s:s + chunk]
        t0, t1, idx = estimator.sampling(o, d, perturb=False, field=field)
        r = render_rays(t0, t1, idx, o.shape[0], radiance_fn(field, o, d))
        out.append(torch.stack([opacity_distance(t0, r["transmittance"], r["alphas"], idx, o.shape[0], x)
                                for x in levels], 1))
    out = torch.cat(out) if out else origins.new_zeros(0, len(levels))
    return out if isinstance(level, (list, tuple)) else out[:, 0]


def nearest_other_view_ends(cams, origins: torch.Tensor, dirs: torch.Tensor, ends: torch.Tensor,
                            mine: torch.Tensor, tol: float) -> torch.Tensor:
    """Per ray, the distance along it of the nearest end point of ANOTHER view that projects onto its
    pixel, if that lies more than ``tol`` in front of its own end ``mine``; +inf otherwise (a free-space
    violation as depth-map fusion tests it). One projection of all end points per view (V passes).

    Args:
        cams: V cameras of H x W pixels. origins, dirs: (V*H*W, 3), unit dirs, view-major, pixel
            (x, y) of view v at ``v*H*W + y*W + x`` (as :func:`~l3d_app.geometry.rays.camera_rays`).
        ends: (V*H*W,) distances whose points are projected (non-finite: none). mine: (V*H*W,) own ends.
    """
    V, hw, W, H = len(cams), cams.height * cams.width, cams.width, cams.height
    view = torch.arange(V, device=ends.device).repeat_interleave(hw)
    ok = torch.isfinite(ends)
    pts, pv = origins[ok] + dirs[ok] * ends[ok, None], view[ok]
    out = torch.full_like(mine, float("inf"))
    for a in range(V):
        uv, z = cams[a].project(pts)
        px, py = uv[0, :, 0].floor().long(), uv[0, :, 1].floor().long()
        m = (pv != a) & (z[0] > 0) & (px >= 0) & (px < W) & (py >= 0) & (py < H)
        t = (pts[m] - cams[a].centers()[0]).norm(dim=-1)
        near = torch.full((hw,), float("inf"), dtype=t.dtype, device=t.device).scatter_reduce(
            0, py[m] * W + px[m], t, "amin")
        own = mine[a * hw:(a + 1) * hw]
        out[a * hw:(a + 1) * hw] = torch.where(near < own - tol, near, torch.full_like(near, float("inf")))
    return out


def near_surface_weight(sdf: torch.Tensor, width: float) -> torch.Tensor:
    """``exp(-|sdf| / width)`` (same shape as ``sdf``, world units in): up to a constant the
    derivative of VolSDF's ``Psi_beta(-f)`` in ``f`` at ``beta = width``, i.e. where an occupancy or
    density loss on free points has a gradient. A proposal for :meth:`FreeRays.sample_resampled`."""
    if not float(width) > 0:
        raise UserError(f"width must be > 0, got {width}")
    return torch.exp(-sdf.abs() / float(width))


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

    def ends_per_ray(self, n_rays: int, covered: Optional[torch.Tensor] = None,
                     extend: float = 0.0) -> torch.Tensor:
        """(n_rays,) where each training ray's free segment ends (world units along its unit direction):
        ``far`` for the rays kept here, -inf (nothing known to be free) for the others. ``covered``
        (n_rays,) bool, e.g. the images' alpha >= 0.5: a covered ray on which the radiance field never
        became opaque gets -inf too (its transparency there contradicts the data: no claim is made).
        ``extend`` (world units, at most the margin the stretches were built with): the ends of the
        stretches that stopped where the field became opaque move this far along their rays (a smaller
        margin for them); the ends at the box exit stay."""
        if self.index is None:
            raise ValueError("these free rays do not know their training-ray indices (built without index)")
        ends = torch.full((int(n_rays),), float("-inf"), dtype=self.far.dtype, device=self.far.device)
        far = self.far
        if extend:
            if self.open_end is None:
                raise ValueError("these free rays do not know which stretches reached the box exit")
            far = torch.where(self.open_end, far, far + float(extend))
        if covered is not None and self.open_end is not None:
            far = torch.where(covered[self.index] & self.open_end, torch.full_like(far, float("-inf")), far)
        return ends.index_put_((self.index,), far)

    def multi_view_cut(self, ends: torch.Tensor, cams, origins: torch.Tensor, dirs: torch.Tensor, margin: float,
                       tol: float = 0.02) -> torch.Tensor:
        """:meth:`ends_per_ray`'s (V*H*W,) ``ends`` cut back where another training view's stretch
        stops in front: each ray that became opaque puts its end point (``far + margin``) into every
        other view (:func:`nearest_other_view_ends`); a ray on whose pixel one lands more than ``tol``
        in front of its own end now ends at that point + ``tol`` - ``margin``. ``cams``, ``origins``,
        unit ``dirs``: the V training views' rays in :func:`nearest_other_view_ends`' order (world units)."""
        if self.index is None or self.open_end is None:
            raise ValueError("these free rays do not know their training-ray indices (built without index)")
        surface = torch.full_like(ends, float("inf"))
        solid = ~self.open_end
        surface = surface.index_put_((self.index[solid],), self.far[solid] + float(margin))
        cut = nearest_other_view_ends(cams, origins, dirs, surface, surface - float(margin), float(tol))
        return torch.minimum(ends, cut + float(tol) - float(margin))

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

    def sample_resampled(self, n: int, candidates: int, proposal: Callable[[torch.Tensor], torch.Tensor],
                         generator: Optional[torch.Generator] = None, shorten: float = 0.0,
                         mix: float = 0.5) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Importance resampling of :meth:`sample`: the same expectation, drawn where it matters.

        ``candidates`` x ``n`` points are drawn as :meth:`sample` draws them, each gets the weight
        ``q = mix * w / mean(w) + (1 - mix)`` with ``w = proposal(points) * length`` >= 0 (e.g. a
        cheap estimate of the loss's gradient there), and ``n`` of them are drawn with
        replacement in proportion to ``q``. Returns (n, 3) points, (n,) lengths and (n,)
        importance weights ``1 / q``: for any ``g``, ``mean(g(points) * weights)`` is an unbiased
        estimate of ``mean(g)`` over :meth:`sample`'s points (defensive mixture: every weight is at
        most ``1 / (1 - mix)``, so the variance is never more than that factor above the uniform
        draw's, and far below it where ``g`` lives on a small part of the free space).
        """
        if not 0.0 <= float(mix) < 1.0:
            raise UserError(f"mix must lie in [0, 1), got {mix}")
        pts, length = self.sample(int(n) * int(candidates), generator, shorten)
        with torch.no_grad():
            w = proposal(pts).clamp_min(0.0) * length
            mean = w.mean()
            q = (float(mix) * w / mean + (1.0 - float(mix))) if float(mean) > 0 else torch.ones_like(w)
            cdf = torch.cumsum(q.double(), 0)
            u = rand((int(n),), generator, pts.device, dtype=torch.float64) * cdf[-1]
            j = torch.searchsorted(cdf, u, right=True).clamp_max(q.shape[0] - 1)
        return pts[j], length[j], (1.0 / q[j]).to(pts.dtype)
