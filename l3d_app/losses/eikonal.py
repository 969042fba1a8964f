"""Eikonal regulariser: a signed distance function has ``|grad f| = 1`` almost everywhere.

``eikonal_loss(grad) = mean((|grad f| - 1)^2)`` over (N, 3) gradients (IGR, Gropp et al. 2020).
The norm is the safe one (``sqrt(max(|g|^2, tiny))``, :func:`~l3d_app.geometry.sdf.safe_norm`),
so a zero gradient -- at an SDF's kinks (a sphere's centre, a box's medial planes) or for a
constant field -- gives the finite loss 1 and a finite (zero) gradient instead of NaN.
:class:`EikonalLoss` is the loss term (``losses.eikonal``) at a render's field samples and at
random points of the scene box.
"""

from __future__ import annotations

from typing import Callable, Optional, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.sdf import safe_norm
from l3d_app.losses.terms import Batch, LossTerm
from l3d_app.registry import LOSS_TERMS
from l3d_app.runtime.random import rand


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


def sdf_and_gradient_at(model, points: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """SDF (N,) and its spatial gradient (N, 3) at points (N, 3), both differentiable w.r.t. the
    model: its exact gradient if it has one (``sdf_features_gradient``), else autograd's."""
    if hasattr(model, "sdf_features_gradient"):
        f, _, grad = model.sdf_features_gradient(points)
        return f, grad
    return model.sdf(points), sdf_gradient(model.sdf, points, create_graph=True)


@LOSS_TERMS.register("eikonal")
class EikonalLoss(LossTerm):
    """:func:`eikonal_loss` of the SDF's gradients at the render's field samples (``out["grad"]``, when the
    field gives them) and at ``points`` uniform random points of the scene box."""

    def __init__(self, weight: float = 0.1, points: int = 1024, start: float = 0.0, until: Optional[float] = None):
        super().__init__(weight, start, until)
        if isinstance(points, bool) or not isinstance(points, int) or points < 0:
            raise UserError(f"the eikonal term's points must be an integer >= 0, got {points!r}")
        self.points = points

    def __call__(self, batch: Batch) -> torch.Tensor:
        state, grads = batch.state, []
        if self.points > 0:
            u = rand((self.points, 3), batch.generator, state.lo.device)
            grads.append(sdf_and_gradient_at(state.model, state.lo + u * (state.hi - state.lo))[1])
        if "grad" in batch.out:
            grads.append(batch.out["grad"].reshape(-1, 3))
        return eikonal_loss(torch.cat(grads))
