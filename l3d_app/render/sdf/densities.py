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
    """

    def __init__(self, beta_init: float, alpha: Optional[float] = None, learnable: bool = False,
                 beta_min: float = 1e-3):
        super().__init__()
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

    def optical_depth(self, sdf: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                      ray_indices: torch.Tensor, widen: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(N,) optical depth ``sigma(f_i) (t_end_i - t_start_i)`` of packed segments (the SDF ``sdf`` at
        ``t_starts``). ``widen`` (N,) (no grad; a coarse sampling pass): ``beta`` is raised to at least
        it and ``alpha`` kept, so a surface thinner than the sample spacing is still seen."""
        if widen is None:
            return self(sdf) * (t_ends - t_starts)
        beta = widen.clamp_min(float(self.beta))
        return volsdf_density(sdf, float(self.alpha), beta) * (t_ends - t_starts)

    def occupancy(self, sdf: torch.Tensor) -> torch.Tensor:
        """How much a point counts as inside, in [0, 1] (same shape): ``Psi_beta(-f)``, the density
        over ``alpha`` (the free-space loss's occupancy)."""
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
    """VolSDF's density with its ``beta`` schedule (config ``density=volsdf``, conf/density/volsdf.yaml).

    Args:
        beta: the initial (``anneal``, ``learnable``) or fixed (``fixed``) Laplace scale (world units).
        mode: ``anneal``: geometric from ``beta`` to ``beta_end`` over ``anneal_fraction`` of the
            steps, then held; ``learnable``: trained with the field (floor ``beta_min``);
            ``fixed``: kept.
        alpha: density inside (1 / world units), or None for ``1 / beta`` (VolSDF).
        lr: the Adam step of ``log(beta - beta_min)`` when ``learnable``.
    """

    warmup_steps = 50
    """The learning-rate warm-up (steps) of a run with this density (``optim.warmup_steps: auto``): a longer
    ramp cost the development scene ``ground`` 0.5 dB and 0.25 points of chamfer (docs/measured/volsdf.md)."""

    def __init__(self, beta: float = 0.3, mode: str = "anneal", beta_end: float = 0.005,
                 anneal_fraction: float = 0.8, beta_min: float = 1e-3, alpha: Optional[float] = None,
                 lr: float = 0.01):
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
                         beta_min=float(beta_min))
        self.mode, self.beta_start, self.beta_end = mode, float(beta), float(beta_end)
        self.anneal_fraction, self.lr = float(anneal_fraction), float(lr)

    def schedule(self, step: float, iters: int) -> None:
        """``anneal``: ``beta = beta_start (beta_end / beta_start)^p``, ``p = min(1, step / (fraction iters))``
        (``step`` may be fractional: a time-budgeted run's nominal step, ``Horizon.nominal``)."""
        if self.mode != "anneal":
            return
        p = min(1.0, step / max(1.0, self.anneal_fraction * int(iters)))
        self.set_beta(self.beta_start * (self.beta_end / self.beta_start) ** p)
