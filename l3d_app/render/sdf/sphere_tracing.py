"""Sphere tracing of signed distance functions (Hart 1996), vectorised over rays.

For rays ``o + t d`` (unit ``d``, ``t`` in world units) and an SDF ``f`` that never
over-estimates the distance to its zero level set, the step ``t += step_scale * f(o + t d)``
can never jump across the surface. The march stops per ray when

* ``|f| < eps``                     -> **hit** at that ``t`` (points are ``o + t d``);
* ``t > far``                        -> **miss** (the ray left its interval, e.g. the scene box);
* ``max_iters`` steps were taken     -> **miss** (e.g. a ray grazing the surface so closely
  that the steps shrink faster than it advances; see below).

Rays that START INSIDE (``f(o + near d) < 0``, more than ``eps`` below zero) are reported as a
hit at ``t = near`` with ``inside = True`` (their point is the ray start): a ray from inside
a solid sees the solid immediately, and marching with a negative step would go backwards.
Callers that want the exit point can trace the negated SDF from there.

Grazing rays: along a ray passing at distance ``b`` from a sphere of radius ``r`` the SDF
has a positive minimum ``b - r`` (a miss: the march passes it and leaves through ``far``)
or goes to zero; for an exactly tangent ray the steps shrink like ``1/n^2`` near the
tangent point, so the ray is reported as a hit (``|f| < eps`` within ``~sqrt(2 r / eps)``
steps) or, with too few iterations, as a miss -- never as a hit elsewhere. A ray that passes
within ``eps`` of the surface counts as touching it (a hit), by the definition above.

Only the rays still marching are evaluated at each iteration (compacted index set), so the
cost is ``sum over iterations of active rays``.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence, Tuple, Union

import torch

from l3d_app.errors import UserError
from l3d_app.render.volume.samplers import ray_aabb

SDFn = Callable[[torch.Tensor], torch.Tensor]
Bound = Union[float, torch.Tensor]


class TraceResult(NamedTuple):
    """Outcome of :func:`sphere_trace` for R rays.

    Attributes:
        points: (R, 3) ``o + t d`` (for misses: the point where marching stopped).
        t: (R,) distance along the ray (world units for unit directions).
        hit: (R,) bool, the ray found the surface (``|f| < eps``) or started inside it.
        inside: (R,) bool, the ray started inside (``f(o + near d) < -eps``; then ``t = near``).
        iterations: (R,) long, SDF evaluations spent on each ray.
    """

    points: torch.Tensor
    t: torch.Tensor
    hit: torch.Tensor
    inside: torch.Tensor
    iterations: torch.Tensor


def _per_ray(value: Bound, n: int, like: torch.Tensor) -> torch.Tensor:
    v = torch.as_tensor(value, dtype=like.dtype, device=like.device).reshape(-1)
    return v.expand(n).clone() if v.numel() == 1 else v.clone()


@torch.no_grad()
def sphere_trace(sdf: SDFn, origins: torch.Tensor, dirs: torch.Tensor, near: Bound = 0.0,
                 far: Bound = 1e3, max_iters: int = 128, eps: float = 1e-4,
                 step_scale: float = 1.0) -> TraceResult:
    """March R rays through ``sdf`` (see the module docstring for hits, misses and inside).

    Args:
        sdf: callable points (N, 3) -> (N,) signed distances (negative inside), world units.
        origins, dirs: (R, 3); ``dirs`` should have unit length (else ``t`` is in units of
            ``|d|`` and the step is only safe for ``|d| <= 1``).
        near, far: floats or (R,) tensors, the interval ``[near, far]`` of ``t`` searched.
        max_iters: maximum SDF evaluations per ray (>= 1).
        eps: hit tolerance on ``|f|`` (world units, > 0).
        step_scale: factor (0, 1] on each step, < 1 for SDFs that may over-estimate the
            distance (e.g. :class:`~l3d_app.geometry.sdf.Superquadric`).
    Returns:
        :class:`TraceResult`. Not differentiable (call the SDF at ``points`` with grad to get
        differentiable values / normals).
    """
    if origins.shape != dirs.shape or origins.shape[-1:] != (3,) or origins.dim() != 2:
        raise UserError(f"sphere_trace needs origins and dirs of shape (R, 3), got "
                        f"{tuple(origins.shape)} and {tuple(dirs.shape)}")
    if int(max_iters) < 1 or not eps > 0 or not 0 < step_scale <= 1:
        raise UserError(f"sphere_trace needs max_iters >= 1, eps > 0 and step_scale in (0, 1], "
                        f"got {max_iters}, {eps}, {step_scale}")
    n = origins.shape[0]
    t = _per_ray(near, n, origins)
    t_far = _per_ray(far, n, origins)
    hit = torch.zeros(n, dtype=torch.bool, device=origins.device)
    inside = torch.zeros_like(hit)
    iters = torch.zeros(n, dtype=torch.long, device=origins.device)
    active = (t <= t_far).nonzero().squeeze(-1)                     # rays still marching
    for k in range(int(max_iters)):
        if active.numel() == 0:
            break
        ta = t[active]
        f = sdf(origins[active] + ta[:, None] * dirs[active]).reshape(-1).to(t.dtype)
        iters[active] += 1
        if k == 0:
            start_in = f < -eps
            inside[active[start_in]] = True
            hit[active[start_in]] = True
        else:
            start_in = torch.zeros_like(f, dtype=torch.bool)
        # a negative value after the start means a step overshot (non-exact SDF): count it as
        # a hit there rather than marching backwards
        done_hit = (f.abs() < eps) | ((f < 0) & ~start_in)
        hit[active[done_hit]] = True
        ta_next = ta + step_scale * f.clamp_min(0.0)
        t[active] = torch.where(done_hit | start_in, ta, ta_next)
        gone = ta_next > t_far[active]
        keep = ~(done_hit | start_in | gone) & torch.isfinite(f)
        t[active[gone & ~done_hit & ~start_in]] = t_far[active[gone & ~done_hit & ~start_in]]
        active = active[keep]
    points = origins + t[:, None] * dirs
    return TraceResult(points=points, t=t, hit=hit, inside=inside, iterations=iters)


def sphere_trace_box(sdf: SDFn, origins: torch.Tensor, dirs: torch.Tensor,
                     box: Tuple[Sequence[float], Sequence[float]], **kwargs) -> TraceResult:
    """:func:`sphere_trace` on each ray's segment inside the axis-aligned ``box`` ((lo), (hi));
    rays that miss the box are misses with ``t = 0``."""
    near, far, in_box = ray_aabb(origins, dirs, box[0], box[1])
    far = torch.where(in_box, far, torch.full_like(far, -1.0))     # t > far at once: no march
    res = sphere_trace(sdf, origins, dirs, near=near, far=far, **kwargs)
    return res._replace(hit=res.hit & in_box, inside=res.inside & in_box,
                        t=torch.where(in_box, res.t, torch.zeros_like(res.t)))


def sdf_normals(sdf: SDFn, points: torch.Tensor) -> torch.Tensor:
    """(N, 3) unit normals ``grad f / |grad f|`` at ``points`` (N, 3) by autograd (no graph kept)."""
    with torch.enable_grad():
        p = points.detach().requires_grad_(True)
        (g,) = torch.autograd.grad(sdf(p).sum(), p)
    return g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)


@torch.no_grad()
def render_sdf_shaded(sdf: SDFn, origins: torch.Tensor, dirs: torch.Tensor,
                      box: Tuple[Sequence[float], Sequence[float]],
                      light_direction: Sequence[float] = (0.4, 1.0, 0.6), background: float = 1.0,
                      max_iters: int = 96, eps: float = 1e-3, step_scale: float = 0.9) -> torch.Tensor:
    """Geometry picture: (R, 3) Lambert-shaded grey (0.25 ambient + 0.75 diffuse) of the
    sphere-traced surface under a directional light, ``background`` where rays miss."""
    res = sphere_trace_box(sdf, origins, dirs, box, max_iters=max_iters, eps=eps, step_scale=step_scale)
    out = torch.full((origins.shape[0], 3), float(background), dtype=origins.dtype, device=origins.device)
    idx = res.hit.nonzero().squeeze(-1)
    if idx.numel():
        n = sdf_normals(sdf, res.points[idx])
        light = torch.as_tensor(light_direction, dtype=n.dtype, device=n.device)
        light = light / light.norm()
        shade = 0.25 + 0.75 * (n @ light).clamp_min(0.0)
        tint = 0.5 + 0.5 * n.abs()                                   # a hint of orientation
        out[idx] = (shade[:, None] * (0.7 + 0.3 * tint)).clamp(0, 1)
    return out
