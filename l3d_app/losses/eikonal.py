"""Eikonal regulariser: a signed distance function has ``|grad f| = 1`` almost everywhere.

``eikonal_loss(grad) = mean((|grad f| - 1)^2)`` over (N, 3) gradients (IGR, Gropp et al. 2020).
The norm is the safe one (``sqrt(max(|g|^2, tiny))``, :func:`~l3d_app.geometry.sdf.safe_norm`),
so a zero gradient -- at an SDF's kinks (a sphere's centre, a box's medial planes) or for a
constant field -- gives the finite loss 1 and a finite (zero) gradient instead of NaN.
"""

from __future__ import annotations

from typing import Callable

import torch

from l3d_app.geometry.sdf import safe_norm


def eikonal_loss(grad: torch.Tensor) -> torch.Tensor:
    """Scalar ``mean((|g| - 1)^2)`` of gradients ``grad`` (N, 3) (unitless)."""
    return ((safe_norm(grad) - 1.0) ** 2).mean()


def sdf_gradient(sdf: Callable[[torch.Tensor], torch.Tensor], points: torch.Tensor,
                 create_graph: bool = True) -> torch.Tensor:
    """(N, 3) spatial gradient of ``sdf`` (points (N, 3) -> (N,)) at ``points``, by autograd;
    ``create_graph`` keeps it differentiable w.r.t. the SDF's parameters."""
    with torch.enable_grad():
        p = points.detach().requires_grad_(True)
        (g,) = torch.autograd.grad(sdf(p).sum(), p, create_graph=create_graph)
    return g


def eikonal_at(sdf: Callable[[torch.Tensor], torch.Tensor], points: torch.Tensor) -> torch.Tensor:
    """Eikonal loss of ``sdf`` at ``points`` (N, 3) (differentiable w.r.t. the SDF's parameters)."""
    return eikonal_loss(sdf_gradient(sdf, points, create_graph=True))
