"""Where to sample along rays: stratified bins, importance (inverse-CDF) resampling, ray-box bounds.

Conventions: R rays, S samples per ray. Rays are ``origin + t * dir`` with ``t`` the
distance along the ray in world units when ``dir`` has unit length (with other directions
``t`` is in units of ``|dir|``). Sample tensors are (R, S), sorted along the last axis.
Randomness only comes from an explicitly passed ``torch.Generator``; with
``perturb=False`` every function here is deterministic.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple, Union

import torch

from l3d_app.errors import UserError
from l3d_app.runtime.random import rand

Bound = Union[float, torch.Tensor]


def _per_ray(value: Bound, n_rays: Optional[int], dtype, device) -> torch.Tensor:
    """A (R, 1) column from a float, a (R,) or a (R, 1) tensor."""
    v = torch.as_tensor(value, dtype=dtype, device=device)
    if v.dim() == 0:
        v = v.reshape(1, 1)
    v = v.reshape(-1, 1)
    if n_rays is not None and v.shape[0] == 1:
        v = v.expand(n_rays, 1)
    return v


def stratified_samples(near: Bound, far: Bound, n_samples: int, n_rays: Optional[int] = None,
                       perturb: bool = False, generator: Optional[torch.Generator] = None,
                       dtype=torch.float32, device=None) -> torch.Tensor:
    """(R, S) sorted distances ``t`` in [near, far] (NeRF's stratified sampling).

    Without ``perturb`` the samples are ``linspace(near, far, S)`` per ray (both ends
    included: this is the course's sampler, used by the box task). With ``perturb`` each
    sample is drawn uniformly in its bin ``[lower_i, upper_i]``, whose edges are the
    midpoints between neighbouring evenly spaced points (``lower_0 = near``,
    ``upper_{S-1} = far``), so the samples stay sorted and inside [near, far].

    Args:
        near, far: floats or (R,) / (R, 1) tensors (world units along unit rays).
        n_samples: S >= 1.
        n_rays: R when ``near`` and ``far`` are both scalars (default 1).
        perturb: jitter inside the bins, drawing from ``generator``.
    """
    if n_samples < 1:
        raise UserError(f"n_samples must be >= 1, got {n_samples}")
    if torch.is_tensor(near):
        dtype, device = near.dtype, near.device
    elif torch.is_tensor(far):
        dtype, device = far.dtype, far.device
    lo, hi = _per_ray(near, None, dtype, device), _per_ray(far, None, dtype, device)
    lo, hi = torch.broadcast_tensors(lo, hi)
    if n_rays is not None and lo.shape[0] == 1:
        lo, hi = lo.expand(n_rays, 1), hi.expand(n_rays, 1)
    steps = torch.linspace(0.0, 1.0, n_samples, dtype=dtype, device=device)
    t = lo + (hi - lo) * steps  # (R, S)
    if perturb and n_samples > 1:
        mids = 0.5 * (t[:, 1:] + t[:, :-1])
        lower = torch.cat([t[:, :1], mids], dim=-1)
        upper = torch.cat([mids, t[:, -1:]], dim=-1)
        u = rand(t.shape, generator, device, dtype)
        t = lower + (upper - lower) * u
    return t


def bin_edges(t: torch.Tensor, near: Optional[Bound] = None, far: Optional[Bound] = None) -> torch.Tensor:
    """(R, S+1) edges of the bins around samples ``t`` (R, S): midpoints, closed by the
    first/last sample (or by ``near``/``far`` when given)."""
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    first = t[:, :1] if near is None else _per_ray(near, t.shape[0], t.dtype, t.device)
    last = t[:, -1:] if far is None else _per_ray(far, t.shape[0], t.dtype, t.device)
    return torch.cat([first, mids, last], dim=-1)


@torch.no_grad()
def sample_pdf(edges: torch.Tensor, weights: torch.Tensor, n_samples: int, perturb: bool = False,
               generator: Optional[torch.Generator] = None, padding: float = 1e-5) -> torch.Tensor:
    """(R, n) sorted samples from the piecewise-constant pdf ``weights`` over bins ``edges``.

    Inverse-CDF sampling. ``padding`` is added to every weight (so rays whose weights are
    all zero sample uniformly, and no bin has exactly zero mass). The CDF is inverted at
    stratified levels ``u_k = (k + 0.5) / n`` without ``perturb`` (deterministic) or
    ``u_k = (k + U(0,1)) / n`` with it; both are increasing, so the output is sorted.
    No gradient flows to ``weights`` or ``edges``.

    Args:
        edges: (R, B+1) increasing bin edges (world units).
        weights: (R, B) non-negative bin weights (need not be normalised).
        n_samples: n >= 1.
    """
    n_rays, n_bins = weights.shape
    dt, dev = edges.dtype, edges.device
    w = weights.detach().to(dt).clamp_min(0.0) + padding
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)
    cdf[:, -1] = 1.0
    k = torch.arange(n_samples, dtype=dt, device=dev).expand(n_rays, n_samples)
    if perturb:
        u = (k + rand(k.shape, generator, dev, dt)) / n_samples
    else:
        u = (k + 0.5) / n_samples
    u = u.contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)      # first cdf > u
    below = (idx - 1).clamp(0, n_bins - 1)
    above = below + 1
    cdf_lo, cdf_hi = cdf.gather(1, below), cdf.gather(1, above)
    e_lo, e_hi = edges.gather(1, below), edges.gather(1, above)
    denom = cdf_hi - cdf_lo
    frac = ((u - cdf_lo) / torch.where(denom > 0, denom, torch.ones_like(denom))).clamp(0.0, 1.0)
    return e_lo + frac * (e_hi - e_lo)


def importance_samples(t: torch.Tensor, weights: torch.Tensor, n_fine: int, perturb: bool = False,
                       generator: Optional[torch.Generator] = None, padding: float = 1e-5,
                       near: Optional[Bound] = None, far: Optional[Bound] = None
                       ) -> torch.Tensor:
    """Hierarchical sampling: (R, S + n_fine) sorted union of coarse ``t`` and new samples.

    The coarse sample ``t_i`` (R, S) with weight ``w_i`` (R, S, e.g. the compositing
    weights of a coarse pass) owns the bin between its neighbours' midpoints (see
    :func:`bin_edges`); ``n_fine`` samples are drawn from the pdf ``w + padding`` over those
    bins by :func:`sample_pdf`, merged with ``t`` and sorted. No gradient flows to the
    returned positions.
    """
    fine = sample_pdf(bin_edges(t, near, far), weights, n_fine, perturb, generator, padding)
    merged, _ = torch.sort(torch.cat([t.detach(), fine], dim=-1), dim=-1)
    return merged


def ray_aabb(origins: torch.Tensor, dirs: torch.Tensor, box_min: Union[Sequence[float], torch.Tensor],
             box_max: Union[Sequence[float], torch.Tensor], min_t: float = 0.0
             ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Intersect rays with an axis-aligned box (slab method).

    Args:
        origins, dirs: (R, 3) (``dirs`` need not be unit; ``t`` is then in units of ``|dir|``).
        box_min, box_max: (3,) box corners (world units).
        min_t: the ray starts at ``t = min_t`` (0: at the origin); ``near`` is at least this.
    Returns:
        near (R,), far (R,), hit (R,) bool. For a hit, the ray is inside the box for
        ``t`` in [near, far] (a ray starting inside has ``near = min_t``). A miss (box not
        crossed, box behind the ray, a ray that only touches an edge or corner, a zero
        direction) has ``hit = False`` and ``near = far = min_t``.

    A zero direction component means the ray is parallel to that slab: the slab holds
    every ``t`` if the origin lies between its planes (boundary included), none otherwise.
    No division by zero happens, so the outputs are always finite.
    """
    dt, dev = origins.dtype, origins.device
    bmin = torch.as_tensor(box_min, dtype=dt, device=dev)
    bmax = torch.as_tensor(box_max, dtype=dt, device=dev)
    parallel = dirs == 0
    safe = torch.where(parallel, torch.ones_like(dirs), dirs)
    t0, t1 = (bmin - origins) / safe, (bmax - origins) / safe
    inf = torch.full_like(t0, float("inf"))
    inside = (origins >= bmin) & (origins <= bmax)
    t_enter = torch.where(parallel, torch.where(inside, -inf, inf), torch.minimum(t0, t1))
    t_exit = torch.where(parallel, torch.where(inside, inf, -inf), torch.maximum(t0, t1))
    near = t_enter.max(dim=-1).values.clamp_min(min_t)
    far = t_exit.min(dim=-1).values
    hit = (far > near) & torch.isfinite(far)   # all-parallel (zero) direction: far = inf
    start = torch.full_like(near, float(min_t))
    near = torch.where(hit, near, start)
    far = torch.where(hit, far, start)
    return near, far, hit
