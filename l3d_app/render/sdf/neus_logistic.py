"""The exercise's NeuS variant: the logistic PDF of the SDF used directly as a volume density.

``sigma(t) = phi_s(f(r(t)))`` with ``phi_s(x) = s sigmoid(s x) sigmoid(-s x)``
(:func:`~l3d_app.render.sdf.neus.logistic_density`, never ``exp(s x)`` raw), composited like any
density: segment ``[t_start, t_end)`` gets the optical depth ``phi_s(f(t_start)) (t_end - t_start)``.
This is NeuS's "naive solution" (Wang et al. 2021, section 3.1), and the reasons NeuS does not use it
are exact here: through a plane crossed at unit speed the total optical depth is ``int phi_s = 1``, so the
surface never becomes more than ``1 - e^-1 = 0.632`` opaque, and the compositing weight
``phi_s(x) exp(-(1 - Phi_s(x)))`` (``x = f``) peaks where ``Phi_s(x) = (sqrt 5 - 1) / 2``, at
``x = ln((1 + sqrt 5) / 2) / s = 0.481 / s`` IN FRONT of the surface, not on it.
"""

from __future__ import annotations

from typing import Optional

import torch

from l3d_app.registry import DENSITIES
from l3d_app.render.sdf.neus import NeuSDensity, logistic_density


@DENSITIES.register("neus_logistic")
class NeuSLogisticDensity(NeuSDensity):
    """``density=neus_logistic``: ``sigma = phi_s(sdf)`` (1 / world units; see the module docstring), with
    NeuS's ``s`` (``mode`` fixed | learnable | anneal, the same arguments as :class:`NeuSDensity`)."""

    def forward(self, sdf: torch.Tensor) -> torch.Tensor:
        """sigma (same shape as ``sdf``), >= 0, peak ``s / 4`` on the surface."""
        return logistic_density(sdf, self.s)

    def optical_depth(self, sdf: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                      ray_indices: torch.Tensor, widen: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(N,) ``phi_s(f(t_start)) (t_end - t_start)`` of packed segments. ``widen`` (N,) world units: the
        peak is widened to at least that (``s <= 1 / widen``) so that coarse samples further apart than
        ``1 / s`` still see it (the proposal's coarse pass)."""
        s = self.s
        if widen is not None:
            s = torch.minimum(torch.as_tensor(s, dtype=sdf.dtype, device=sdf.device), 1.0 / widen.clamp_min(1e-12))
        return logistic_density(sdf, s) * (t_ends - t_starts)

    def rgb_key(self) -> str:
        return "tau"
