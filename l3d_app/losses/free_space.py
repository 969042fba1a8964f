"""Known free space: what a training ray passes through before any surface is empty.

The free-space stage (:mod:`~l3d_app.stages.free_space`) reads, off a radiance field fitted to the
same images, each training ray's free stretch (:class:`~l3d_app.render.volume.free_space.FreeRays`);
two loss terms tell the SDF so:

- :class:`FreePointsLoss` (``losses.free_points``): at points drawn on the stretches, the density's
  occupancy x the stretch's length (:func:`free_stretch_occupancy`: VolSDF's ``Psi_beta(-f)``, NeuS's
  ``sigmoid(-s f)``);
- :class:`FreeRaysLoss` (``losses.free_rays``): the opacity the render's own samples accumulate before
  each batch ray's stretch end (:func:`opacity_before`): its gradient falls on the samples that carry
  the ray's weight, so a thin sheet in front of the end gets all of it.

Both end the stretches ``margin_beta`` transition widths (VolSDF's ``beta``, NeuS's ``1 / s``) early:
a true surface's own tail in front of it is not carved. Nothing is said about what no ray passes
through (hidden interiors, an unseen underside).

``termination_distance(depth, opacity, near, far)``: a radiance field's expected distance along each ray
to where it stops, a ray that passes counted as stopping at the box exit; its gradient moves density
towards the camera (the stage's front prior, where a uniform face does not pin the depth).
"""

from __future__ import annotations

from typing import Optional

import torch

from l3d_app.errors import UserError
from l3d_app.losses.terms import Batch, LossTerm
from l3d_app.registry import LOSS_TERMS
from l3d_app.render.sdf.densities import transition_width


def free_stretch_occupancy(f: torch.Tensor, length: torch.Tensor, density) -> torch.Tensor:
    """Scalar ``mean(density.occupancy(f) x length)`` at (N,) SDF values ``f`` of points on known-free
    stretches of (N,) ``length`` (world units): for VolSDF ``Psi_beta(-f)`` x length (the stretch's
    optical depth over alpha, a 1-point estimate), for NeuS ``sigmoid(-s f)`` x length."""
    return (density.occupancy(f) * length).mean()


def opacity_before(weights: torch.Tensor, t_starts: torch.Tensor, ray_indices: torch.Tensor, ends: torch.Tensor,
                   n_rays: int) -> torch.Tensor:
    """(R,) per ray, the summed compositing weights of its packed samples that start before its end.

    Args:
        weights: (N,) each sample's weight ``T_i (1 - exp(-tau_i))`` (a render's ``weights``).
        t_starts: (N,) each sample's start along its ray (world units). ray_indices: (N,) its ray.
        ends: (R,) each ray's free-stretch end (world units; -inf: none, the ray contributes 0;
            +inf: all of it). n_rays: R.
    Returns:
        (R,) the opacity accumulated in front of ``ends`` (in [0, 1] for a render's weights), to the
        sample boundary at or after the end (a sample that straddles it counts whole).
    """
    inside = (t_starts < ends.index_select(0, ray_indices)).to(weights.dtype)
    return weights.new_zeros(int(n_rays)).index_add(0, ray_indices, weights * inside)


def termination_distance(depth: torch.Tensor, opacity: torch.Tensor, near: torch.Tensor,
                         far: torch.Tensor) -> torch.Tensor:
    """(R,) expected stopping distance past the box entry: ``depth + (1 - opacity) * far - near``.

    Args:
        depth: (R,) ``sum_i w_i t_i`` of a render (unnormalised, world units along the ray).
        opacity: (R,) ``sum_i w_i`` in [0, 1].
        near, far: (R,) the box entry and exit distances of each ray.
    Returns:
        (R,) in [0, far - near] when the samples lie in the box: the mean of ``t - near`` over where
        the ray stops, the light that passes counted at the exit. Lower where density sits nearer."""
    return depth + (1.0 - opacity) * far - near


def _margin_beta(value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
        raise UserError(f"margin_beta must be a number >= 0 (transition widths), got {value!r}")
    return float(value)


@LOSS_TERMS.register("free_points")
class FreePointsLoss(LossTerm):
    """:func:`free_stretch_occupancy` at ``points`` points, each uniform on the known free stretch of a
    uniformly drawn training ray, the stretches ended ``margin_beta`` transition widths early."""

    needs = "free_rays"

    def __init__(self, weight: float = 0.33, points: int = 1024, margin_beta: float = 1.0, start: float = 0.0,
                 until: Optional[float] = None):
        super().__init__(weight, start, until)
        if isinstance(points, bool) or not isinstance(points, int) or points < 1:
            raise UserError(f"the free-points term's points must be a positive integer, got {points!r}")
        self.points, self.margin_beta = points, _margin_beta(margin_beta)

    def setup(self, state) -> bool:
        self.free = state.products.get(self.needs)
        return self.free is not None and len(self.free) > 0

    def __call__(self, batch: Batch) -> torch.Tensor:
        dens = batch.state.density
        shorten = self.margin_beta * transition_width(dens) if self.margin_beta > 0 else 0.0
        pts, length = self.free.sample(self.points, batch.generator, shorten)
        return free_stretch_occupancy(batch.state.model.sdf(pts), length, dens)


@LOSS_TERMS.register("free_rays")
class FreeRaysLoss(LossTerm):
    """The batch mean of :func:`opacity_before`: the render's opacity before each ray's free-stretch end
    less ``margin_beta`` transition widths (a ray the images' alpha covers on which the radiance field never
    became opaque makes no claim: :meth:`~l3d_app.render.volume.free_space.FreeRays.ends_per_ray`)."""

    needs = "free_rays"

    def __init__(self, weight: float = 0.03, margin_beta: float = 3.0, start: float = 0.0,
                 until: Optional[float] = None):
        super().__init__(weight, start, until)
        self.margin_beta = _margin_beta(margin_beta)

    def setup(self, state) -> bool:
        free = state.products.get(self.needs)
        if free is None:
            return False
        self.ends = free.ends_per_ray(state.rays.n, state.rays.covered)
        return True

    def __call__(self, batch: Batch) -> torch.Tensor:
        out = batch.out
        ends = self.ends[batch.rays] - self.margin_beta * transition_width(batch.state.density)
        return opacity_before(out["weights"], out["t"], out["ray_indices"], ends, batch.rays.shape[0]).mean()
