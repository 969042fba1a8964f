"""NeuS (Wang et al. 2021): SDF -> opacity through the logistic CDF, in the sigmoid form.

With ``Phi_s(x) = sigmoid(s x)`` (the logistic CDF of scale ``1/s``) and SDF values ``f_i``,
``f_{i+1}`` at the two ends of a ray segment, NeuS's discrete opacity is::

    alpha_i = max((Phi_s(f_i) - Phi_s(f_{i+1})) / Phi_s(f_i), 0)
            = 1 - exp(min(log Phi_s(f_{i+1}) - log Phi_s(f_i), 0))

and the optical depth of the segment (``alpha = 1 - exp(-tau)``) is simply
``tau_i = max(log Phi_s(f_i) - log Phi_s(f_{i+1}), 0)``. Everything here uses
``logsigmoid`` (``log Phi_s(x) = -softplus(-s x)``), never ``exp(s x)``: with ``s`` up to 1e4
and ``|f|`` up to 1e3 (``s f = 1e7``) values and gradients stay finite and accurate, where the
raw ``(Phi(a) - Phi(b)) / Phi(a)`` loses everything to 0/0 once both sigmoids underflow.

``logistic_density`` is the logistic PDF ``phi_s(x) = s sigmoid(s x) sigmoid(-s x)`` (NeuS's
"S-density"), also in the product-of-sigmoids form (``s e^{-sx} / (1 + e^{-sx})^2`` overflows).
"""

from __future__ import annotations

import math
from typing import Optional, Union

import torch
import torch.nn.functional as F

from l3d_app.errors import UserError
from l3d_app.registry import DENSITIES

Scalar = Union[float, torch.Tensor]


def logistic_cdf(x: torch.Tensor, s: Scalar) -> torch.Tensor:
    """``Phi_s(x) = sigmoid(s x)`` elementwise, in [0, 1] (``s`` > 0: inverse scale, 1 / units of x)."""
    return torch.sigmoid(s * x)


def log_logistic_cdf(x: torch.Tensor, s: Scalar) -> torch.Tensor:
    """``log Phi_s(x) = logsigmoid(s x) <= 0``: exact for large negative ``s x`` (``~ s x``)."""
    return F.logsigmoid(s * x)


def logistic_density(x: torch.Tensor, s: Scalar) -> torch.Tensor:
    """Logistic PDF ``phi_s(x) = s sigmoid(s x) sigmoid(-s x)`` (same shape as ``x``), >= 0,
    peak ``s / 4`` at 0, integral 1."""
    return s * torch.sigmoid(s * x) * torch.sigmoid(-s * x)


def neus_optical_depth(sdf_start: torch.Tensor, sdf_end: torch.Tensor, s: Scalar) -> torch.Tensor:
    """Optical depth ``tau = max(log Phi_s(f_start) - log Phi_s(f_end), 0)`` of ray segments.

    Args:
        sdf_start, sdf_end: SDF at each segment's near / far end (world units), same shape.
        s: inverse scale (1 / world units) > 0; a float or a broadcastable tensor (may require grad).
    Returns:
        tau >= 0, same shape; ``alpha = 1 - exp(-tau)`` (see :func:`neus_alpha`); a segment
        where the SDF rises (leaving a surface) gets 0.
    """
    return (log_logistic_cdf(sdf_start, s) - log_logistic_cdf(sdf_end, s)).clamp_min(0.0)


def neus_alpha(sdf_start: torch.Tensor, sdf_end: torch.Tensor, s: Scalar) -> torch.Tensor:
    """NeuS discrete opacity ``max((Phi_s(f_start) - Phi_s(f_end)) / Phi_s(f_start), 0)`` in
    [0, 1], as ``-expm1(-tau)`` of :func:`neus_optical_depth`."""
    return -torch.expm1(-neus_optical_depth(sdf_start, sdf_end, s))


@DENSITIES.register("neus")
class NeuSDensity(torch.nn.Module):
    """NeuS's opacity as a density module (config ``density=neus``).

    Segment ``i`` of a ray has optical depth ``max(log Phi_s(f_i) - log Phi_s(f_{i+1}), 0)``
    (:func:`neus_optical_depth`; ``f_{i+1}`` the SDF at the ray's next sample); the last
    segment of each ray gets 0. A ray that passes a surface at height ``h`` without entering it
    collects ``log Phi_s(f_start) - log Phi_s(h)``: under half the opacity for any ``h > 0``, so a
    silhouette lies ON the zero level set (VolSDF's lies outside it: docs/neural_fields.md).

    Args:
        s: the inverse scale (1 / world units, > 0): fixed (``mode=fixed``), the initial value
            (``learnable``, trained as ``log s``; ``anneal``).
        mode: ``fixed`` | ``learnable`` | ``anneal``: geometric from ``s`` to ``s_end`` over
            ``anneal_fraction`` of the steps, then held (:meth:`schedule`).
        lr: the Adam step of ``log s`` when ``learnable``.
    """

    warmup_steps = 150
    """The learning-rate warm-up (steps) of a run with this density (``optim.warmup_steps: auto``): with 50 NeuS
    lost its surface on the development scene ``dev`` in 3 of 9 runs, with 150 in none (docs/measured/volsdf.md)."""

    def __init__(self, s: float = 64.0, mode: str = "fixed", s_end: float = 200.0,
                 anneal_fraction: float = 0.8, lr: float = 0.01):
        super().__init__()
        mode = str(mode)
        if mode not in ("fixed", "learnable", "anneal"):
            raise UserError(f"NeuS s mode must be fixed, learnable or anneal, got {mode!r}")
        if not float(s) > 0:
            raise UserError(f"s must be > 0, got {s}")
        if mode == "anneal" and not float(s_end) > 0:
            raise UserError(f"s mode anneal needs s_end > 0, got {s_end}")
        if not 0.0 <= float(anneal_fraction) <= 1.0:
            raise UserError(f"anneal_fraction must be in [0, 1], got {anneal_fraction}")
        log_s = torch.tensor(math.log(float(s)))
        if mode == "learnable":
            self.log_s = torch.nn.Parameter(log_s)
        else:
            self.register_buffer("log_s", log_s)
        self.mode, self.s_start, self.lr = mode, float(s), float(lr)
        self.s_end = float(s_end)
        self.anneal_fraction = float(anneal_fraction)
        self.fixed_s = None if mode == "learnable" else float(s)
        self.register_load_state_dict_post_hook(NeuSDensity._s_from_loaded_state)

    @staticmethod
    def _s_from_loaded_state(module: "NeuSDensity", _incompatible) -> None:
        """After ``load_state_dict`` the state's ``log_s`` is the ``s`` in use (an annealed run's checkpoint:
        its last ``s``), not the configured start: a loaded run renders as it was trained (render_path,
        ``resume=true`` of a finished run)."""
        if module.fixed_s is not None:
            module.fixed_s = float(torch.exp(module.log_s))

    @property
    def s(self):
        """Inverse scale (a float when fixed or annealed, a scalar tensor when learnable)."""
        return self.fixed_s if self.fixed_s is not None else torch.exp(self.log_s)

    def optical_depth(self, sdf: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                      ray_indices: torch.Tensor, widen: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(N,) optical depth of packed segments (``widen`` is not needed: a sign change between
        two samples is seen at any ``s``)."""
        tau = neus_optical_depth(sdf[:-1], sdf[1:], self.s)
        same_ray = ray_indices[1:] == ray_indices[:-1]
        tau = torch.where(same_ray, tau, torch.zeros_like(tau))
        return torch.cat([tau, tau.new_zeros(1)]) if sdf.numel() else sdf.new_zeros(0)

    def occupancy(self, sdf: torch.Tensor) -> torch.Tensor:
        """How much a point counts as inside, in [0, 1] (same shape): ``Phi_s(-f) = sigmoid(-s f)``
        (the free-space loss's ``occupancy``)."""
        return logistic_cdf(-sdf, self.s)

    def rgb_key(self) -> str:
        return "tau"

    def schedule(self, step: float, iters: int) -> None:
        """``anneal``: ``s = s_start (s_end / s_start)^p``, ``p = min(1, step / (fraction iters))``
        (``step`` may be fractional: a time-budgeted run's nominal step); otherwise nothing."""
        if self.mode != "anneal":
            return
        p = min(1.0, step / max(1.0, self.anneal_fraction * int(iters)))
        self.fixed_s = self.s_start * (self.s_end / self.s_start) ** p
        self.log_s.fill_(math.log(self.fixed_s))

    def stats(self) -> dict:
        return {"s": float(self.s)}
