"""SDF -> density/opacity conversions, written so that no exponential can overflow.

VolSDF (Yariv et al. 2021) turns a signed distance ``d`` into a density
``sigma = alpha * Psi_beta(-d)`` where ``Psi_beta`` is the CDF of a zero-mean Laplace
distribution with scale ``beta``::

    Psi_beta(x) = 0.5 * exp(x / beta)          for x <= 0
                = 1 - 0.5 * exp(-x / beta)     for x > 0

Each branch is evaluated on an argument clamped to its own half-line, so the exponent is
always <= 0: nothing overflows for any ``beta > 0`` and ``|x|`` (1e3 / 1e-4 = 1e7 is just
``exp(-1e7) = 0``), and the branch that ``torch.where`` discards has a finite value and a
finite gradient, so no NaN leaks into autograd.
"""

from __future__ import annotations

import math
from typing import Optional, Union

import torch

from l3d_app.errors import UserError
from l3d_app.registry import DENSITIES

Scalar = Union[float, torch.Tensor]


def laplace_cdf(x: torch.Tensor, beta: Scalar) -> torch.Tensor:
    """CDF of a Laplace(0, beta) distribution, elementwise, values in [0, 1].

    Args:
        x: any shape (e.g. world units when ``x = -sdf``).
        beta: scale > 0 (same units as ``x``); a float or a tensor broadcastable to ``x``
            (it may require grad).
    Returns:
        tensor of ``x``'s shape: ``0.5 exp(x/beta)`` for ``x <= 0``, ``1 - 0.5 exp(-x/beta)``
        for ``x > 0``. Derivative ``0.5 exp(-|x|/beta) / beta`` everywhere (also at 0).
    """
    neg = 0.5 * torch.exp(x.clamp_max(0.0) / beta)          # exponent <= 0
    pos = 1.0 - 0.5 * torch.exp(-x.clamp_min(0.0) / beta)   # exponent <= 0
    return torch.where(x <= 0, neg, pos)


def laplace_cdf_integral(x: torch.Tensor, beta: Scalar) -> torch.Tensor:
    """``G(x) = integral of laplace_cdf from -inf to x``, elementwise (units of ``x``):
    ``0.5 beta exp(x/beta)`` for ``x <= 0``, ``x + 0.5 beta exp(-x/beta)`` for ``x > 0`` (both exponents <= 0)."""
    neg = 0.5 * beta * torch.exp(x.clamp_max(0.0) / beta)
    pos = x.clamp_min(0.0) + 0.5 * beta * torch.exp(-x.clamp_min(0.0) / beta)
    return torch.where(x <= 0, neg, pos)


def mean_laplace_cdf(a: torch.Tensor, b: torch.Tensor, beta: Scalar) -> torch.Tensor:
    """The mean of ``Psi_beta(-f)`` over a segment along which the SDF ``f`` runs linearly from ``a``
    to ``b`` (same shapes): ``(G(-b) - G(-a)) / (a - b)`` (:func:`laplace_cdf_integral`); where
    ``|a - b|`` < 1e-2 beta, ``Psi_beta(-(a + b) / 2)`` (error O((a - b)^2 / beta^2)). Values in [0, 1];
    gradients finite for any inputs (the discarded branch divides by 1)."""
    d = a - b
    small = d.abs() < 1e-2 * beta
    ratio = (laplace_cdf_integral(-b, beta) - laplace_cdf_integral(-a, beta)) / torch.where(small, torch.ones_like(d), d)
    return torch.where(small, laplace_cdf(-0.5 * (a + b), beta), ratio.clamp(0.0, 1.0))


def linear_segment_ends(sdf: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                        ray_indices: torch.Tensor) -> torch.Tensor:
    """(N,) the SDF at each packed segment's END, interpolated linearly between its start sample and
    the next sample of the same ray (segments sorted along each ray, samples at ``t_starts``); the
    last segment of a ray, or one whose next sample does not lie after it, keeps its start value."""
    if sdf.numel() == 0:
        return sdf
    same = torch.zeros_like(ray_indices, dtype=torch.bool)
    same[:-1] = ray_indices[1:] == ray_indices[:-1]
    f_next = torch.cat([sdf[1:], sdf[-1:]])
    gap = torch.cat([t_starts[1:], t_ends[-1:]]) - t_starts
    ok = same & (gap > 0)
    frac = ((t_ends - t_starts) / torch.where(ok, gap, torch.ones_like(gap))).clamp(0.0, 1.0)
    return torch.where(ok, sdf + (f_next - sdf) * frac, sdf)


def distance_along_ray(sdf: torch.Tensor, grad: torch.Tensor, dirs: torch.Tensor, floor: float) -> torch.Tensor:
    """(N,) the SDF ``sdf`` (N,) divided by how fast it falls along the ray: ``f / c`` with
    ``c = |grad f . d| / (|grad f| |d|)`` (``grad`` (N, 3), ``dirs`` (N, 3)), ``c`` floored at ``floor``
    (in (0, 1]) and held out of the gradient (``d(f/c)/df = 1/c``; nothing flows into the normal).

    Near a locally planar surface ``f / c`` is the distance to it along the ray (world units), whatever
    the angle; a ray that passes a convex surface (radius ``R``) at distance ``h`` has
    ``f / c >= sqrt(2 h R)`` (until ``c`` reaches the floor). A zero gradient gives ``c = floor``.
    """
    with torch.no_grad():
        norms = (grad.norm(dim=-1) * dirs.norm(dim=-1)).clamp_min(1e-12)
        c = ((grad * dirs).sum(-1).abs() / norms).clamp(float(floor), 1.0)
    return sdf / c


def transition_width(density) -> float:
    """How wide a ``DENSITIES`` module's surface transition is (world units): VolSDF's ``beta``, NeuS's ``1 / s``."""
    return float(density.beta) if hasattr(density, "beta") else 1.0 / float(density.s)


def volsdf_density(sdf: torch.Tensor, alpha: Scalar, beta: Scalar) -> torch.Tensor:
    """VolSDF density ``alpha * Psi_beta(-sdf)`` (same shape as ``sdf``).

    ``alpha`` is the density inside the surface (1 / world units when used as sigma),
    ``beta`` the smoothing length (world units). The box task uses this value directly as
    a per-sample opacity (the course's rule), see ``l3d_app/tasks/box.py``.
    """
    return alpha * laplace_cdf(-sdf, beta)


class LaplaceDensity(torch.nn.Module):
    """VolSDF density with a fixed or learnable ``beta`` and ``alpha`` fixed or tied to ``1/beta``.

    ``beta = beta_min + exp(rho)`` (``rho`` a parameter when ``learnable``, initialised so that
    ``beta`` starts at ``beta_init``; a buffer otherwise), ``alpha = alpha`` if given, else
    ``1 / beta`` (VolSDF's choice: the density inside is the inverse of the smoothing length, so
    the opacity across the surface does not depend on ``beta``). ``forward(sdf) -> sigma``
    (1 / world units), same shape as ``sdf``; never overflows (:func:`volsdf_density`).

    Args:
        beta_init: initial (or fixed) Laplace scale, world units, > beta_min.
        alpha: density inside (1 / world units) or None for ``1 / beta``.
        learnable: train ``beta`` (with the field's optimiser).
        beta_min: floor of ``beta`` (world units, >= 0).
        quadrature: ``left`` or ``linear`` (:meth:`optical_depth`).
        along_ray: the density of the distance to the surface along the ray instead of the SDF
            (:meth:`sdf_along_ray`, :func:`distance_along_ray`): a surface seen at a grazing angle has
            the transition in ``t`` of one seen head-on, so silhouettes do not appear outside the zero
            level set (the bias that shrinks a fitted convex surface by ``~beta ln(sqrt(pi R / 2 beta))``).
        along_ray_floor: with ``along_ray``, the least ``|n . d|`` (in (0, 1]).
    """

    def __init__(self, beta_init: float = 0.1, alpha: Optional[float] = None, learnable: bool = True,
                 beta_min: float = 1e-4, quadrature: str = "left", along_ray: bool = False,
                 along_ray_floor: float = 0.1):
        super().__init__()
        if quadrature not in ("left", "linear"):
            raise UserError(f"quadrature must be left or linear, got {quadrature!r}")
        if not 0.0 < float(along_ray_floor) <= 1.0:
            raise UserError(f"along_ray_floor must lie in (0, 1], got {along_ray_floor}")
        self.quadrature, self.along_ray, self.along_ray_floor = quadrature, bool(along_ray), float(along_ray_floor)
        if not beta_init > beta_min >= 0:
            raise UserError(f"LaplaceDensity needs beta_init > beta_min >= 0, got {beta_init}, {beta_min}")
        if alpha is not None and not alpha > 0:
            raise UserError(f"alpha must be > 0 or None (1 / beta), got {alpha}")
        rho = torch.tensor(math.log(float(beta_init) - float(beta_min)))
        if learnable:
            self.rho = torch.nn.Parameter(rho)
        else:
            self.register_buffer("rho", rho)
        self.beta_min, self.fixed_alpha = float(beta_min), alpha

    @torch.no_grad()
    def set_beta(self, value: float) -> None:
        """Set beta (world units, > beta_min), e.g. from an annealing schedule."""
        if not value > self.beta_min:
            raise UserError(f"beta must be > beta_min = {self.beta_min}, got {value}")
        self.rho.fill_(math.log(float(value) - self.beta_min))

    @property
    def beta(self) -> torch.Tensor:
        """Current beta (scalar tensor, world units)."""
        return self.beta_min + torch.exp(self.rho)

    @property
    def alpha(self) -> torch.Tensor:
        """Current alpha (scalar tensor, 1 / world units)."""
        return 1.0 / self.beta if self.fixed_alpha is None else torch.as_tensor(float(self.fixed_alpha))

    def forward(self, sdf: torch.Tensor) -> torch.Tensor:
        beta = self.beta
        alpha = 1.0 / beta if self.fixed_alpha is None else float(self.fixed_alpha)
        return volsdf_density(sdf, alpha, beta)

    def sdf_along_ray(self, sdf: torch.Tensor, grad: Optional[torch.Tensor], dirs: torch.Tensor) -> torch.Tensor:
        """What the density reads at samples (N,) with the field's gradient ``grad`` (N, 3) and ray
        directions ``dirs`` (N, 3): ``sdf`` itself, or with ``along_ray`` :func:`distance_along_ray`
        (which needs ``grad``: ValueError without it)."""
        if not self.along_ray:
            return sdf
        if grad is None:
            raise ValueError("along_ray needs the field's gradient at the samples (a field with an exact gradient)")
        return distance_along_ray(sdf, grad, dirs, self.along_ray_floor)

    def optical_depth(self, sdf: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                      ray_indices: torch.Tensor, widen: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(N,) optical depth of packed segments (sorted along each ray, the SDF ``sdf`` at ``t_starts``).

        ``quadrature`` ``left``: ``sigma(f_i) (t_end_i - t_start_i)``; ``linear``: ``alpha`` x the
        segment's length x the exact mean of ``Psi_beta(-f)`` along it with ``f`` linear from ``f_i``
        towards the ray's next sample (:func:`linear_segment_ends`, :func:`mean_laplace_cdf`): a
        surface between two samples is integrated, not read at one point, so the result does not
        hinge on where the samples fall when ``beta`` is below their spacing.
        ``widen`` (N,) (no grad; a coarse sampling pass): ``beta`` is raised to at least it and
        ``alpha`` kept, so a surface thinner than the sample spacing is still seen (left rule).
        """
        if widen is None and self.quadrature == "linear":
            beta = self.beta
            alpha = 1.0 / beta if self.fixed_alpha is None else float(self.fixed_alpha)
            f_end = linear_segment_ends(sdf, t_starts, t_ends, ray_indices)
            return alpha * mean_laplace_cdf(sdf, f_end, beta) * (t_ends - t_starts)
        if widen is None:
            return self(sdf) * (t_ends - t_starts)
        beta = widen.clamp_min(float(self.beta))
        return volsdf_density(sdf, float(self.alpha), beta) * (t_ends - t_starts)

    def occupancy(self, sdf: torch.Tensor) -> torch.Tensor:
        """How much a point counts as inside, in [0, 1] (same shape): ``Psi_beta(-f)``, the density
        over ``alpha`` (the free-space loss's ``occupancy``)."""
        return self(sdf) / self.alpha

    def rgb_key(self) -> str:
        """What the density gives the renderer per sample: ``sigma`` (times the segment length)."""
        return "sigma"

    def schedule(self, step: int, iters: int) -> None:
        """Per-step hook (no-op: a fixed or learnable beta)."""
        return None

    def stats(self) -> dict:
        return {"beta": float(self.beta), "alpha": float(self.alpha)}


@DENSITIES.register("volsdf")
class VolSDFDensity(LaplaceDensity):
    """VolSDF's density with its ``beta`` schedule (config ``density=volsdf``).

    Args:
        beta: the initial (``anneal``, ``learnable``) or fixed (``fixed``) Laplace scale (world units).
        mode: ``anneal``: geometric from ``beta`` to ``beta_end`` over ``anneal_fraction`` of the
            steps, then held; ``learnable``: trained with the field (floor ``beta_min``);
            ``fixed``: kept.
        alpha: density inside (1 / world units), or None for ``1 / beta`` (VolSDF).
        quadrature: ``left`` (the density at each segment's start) or ``linear`` (its exact mean along
            a linear SDF to the next sample): :meth:`LaplaceDensity.optical_depth`.
        along_ray, along_ray_floor: the density of the distance to the surface along the ray
            (:meth:`LaplaceDensity.sdf_along_ray`).
    """

    def __init__(self, beta: float = 0.1, mode: str = "anneal", beta_end: float = 0.005,
                 anneal_fraction: float = 0.8, beta_min: float = 1e-3, alpha: Optional[float] = None,
                 quadrature: str = "left", along_ray: bool = False, along_ray_floor: float = 0.1):
        if mode not in ("anneal", "learnable", "fixed"):
            raise UserError(f"density mode must be anneal, learnable or fixed, got {mode!r}")
        for key, value in (("beta", beta), ("beta_end", beta_end)):
            if not float(value) > 0:
                raise UserError(f"{key} must be > 0 (world units), got {value}")
        if not 0 <= float(beta_min) < min(float(beta), float(beta_end)):
            raise UserError(f"beta_min must be in [0, min(beta, beta_end)), got {beta_min} "
                             f"(beta={beta}, beta_end={beta_end})")
        if not 0.0 <= float(anneal_fraction) <= 1.0:
            raise UserError(f"anneal_fraction must be in [0, 1], got {anneal_fraction}")
        super().__init__(float(beta), None if alpha is None else float(alpha), learnable=mode == "learnable",
                         beta_min=float(beta_min), quadrature=str(quadrature), along_ray=bool(along_ray),
                         along_ray_floor=float(along_ray_floor))
        self.mode, self.beta_start, self.beta_end = mode, float(beta), float(beta_end)
        self.anneal_fraction = float(anneal_fraction)

    def schedule(self, step: float, iters: int) -> None:
        """``anneal``: ``beta = beta_start (beta_end / beta_start)^p``, ``p = min(1, step / (fraction iters))``
        (``step`` may be fractional: a time-budgeted run's nominal step, ``Horizon.nominal``)."""
        if self.mode != "anneal":
            return
        p = min(1.0, step / max(1.0, self.anneal_fraction * int(iters)))
        self.set_beta(self.beta_start * (self.beta_end / self.beta_start) ** p)
