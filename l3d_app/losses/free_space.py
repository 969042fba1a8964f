"""Occupied-volume priors for SDF fields: the least solid the images allow.

``occupied_volume(f) = mean(relu(-f))`` over SDF values ``f`` (N,) at points drawn uniformly in
the scene box: the box volume times this is the integral of the depth below the surface over
the solid, ``|box| * E[max(0, -f)]`` (world units^4 for a unit-gradient SDF). Its gradient
raises ``f`` only INSIDE the solid, each point by ``1/N``, so a solid nothing in the images
holds up (the initial sphere's leftover where no camera looks, a mound the colour network can
paint over) is pushed towards the least surface; the push on a thin plate is small (its depth
is at most half its thickness). Free space (``f >= 0``) costs nothing and gets no gradient.
Measured on the development scene ``ground`` (docs/measured/volsdf.md): neither prior removed
the mound in view, the fraction form cleared the leftover where no ray passes at a cost in
PSNR and surface roughness, and larger weights were worse; volsdf keeps them off.

``free_stretch_loss(kind, f, length, density)``: the same idea where the images SAY a point is
empty (a point on a training ray before any surface, ``render/volume/free_space.py``): ``outside``
``mean(relu(-f))``, ``density`` the stretch's optical depth (1-point estimate, VolSDF only),
``occupancy`` the density module's occupancy x length (VolSDF's ``Psi_beta(-f)``, NeuS's ``Phi_s(-f)``).

``opacity_before(weights, t, ray_indices, ends, n_rays)``: the same claim on whole rays: the opacity a
render's own samples accumulate before each ray's free-stretch end. Its gradient falls on the samples
that carry the ray's weight (a thin sheet in front of the end gets all of it), with no extra points.
``log_depth(opacity)``: ``log(1 + tau)`` of the optical depth that opacity stands for, a form of it that
does not saturate behind an opaque lid (``free_space.ray_loss=log_depth``).

``termination_distance(depth, opacity, near, far)``: a radiance field's expected distance along each ray
to where it stops, a ray that passes counted as stopping at the box exit; its gradient moves density
towards the camera. On rays the images say end on a surface it is a prior for the front-most density the
images allow (the free-space stage's ``w_front``: where a uniform face does not pin the depth).

``occupied_fraction(f, softness) = mean(sigmoid(-f / softness))``: the share of the box inside
the solid, smoothed over ``softness`` world units; its gradient sits at the boundary
(``|f|`` within a few ``softness``) and leaves the inside's values alone.
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from l3d_app.errors import UserError


def occupied_volume(sdf: torch.Tensor) -> torch.Tensor:
    """Scalar ``mean(max(0, -sdf))`` of SDF values (world units) at uniform box points."""
    return torch.relu(-sdf).mean()


def occupied_fraction(sdf: torch.Tensor, softness: float) -> torch.Tensor:
    """Scalar ``mean(sigmoid(-sdf / softness))`` (unitless, in [0, 1]) of SDF values at uniform box
    points; ``softness`` > 0 in world units."""
    if not float(softness) > 0:
        raise UserError(f"softness must be > 0, got {softness}")
    return torch.sigmoid(-sdf / float(softness)).mean()


def fade_to_zero(progress: float, until) -> float:
    """A weight's factor at ``progress`` (step / steps): 1 throughout when
    ``until`` is None, else falling linearly from 1 at the start to 0 at ``until``."""
    if until is None:
        return 1.0
    return max(0.0, 1.0 - float(progress) / float(until))


def free_stretch_loss(kind: str, f: torch.Tensor, length: torch.Tensor, density,
                      weights: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The loss at (N,) SDF values ``f`` of points on known-free stretches of (N,) ``length``
    (world units): ``outside`` mean(relu(-f)); ``density`` the mean optical depth of a stretch
    (density(f) x length, 1-point estimate; a density per point: VolSDF); ``occupancy``
    ``density.occupancy(f) x length`` (VolSDF: the same over alpha, Psi_beta(-f) x length, as strong as
    ``density`` early, weaker as beta anneals; NeuS: sigmoid(-s f) x length). ``weights`` (N,): importance weights
    of resampled points (:meth:`~l3d_app.render.volume.free_space.FreeRays.sample_resampled`), each
    point's term multiplied by its weight (None: 1)."""
    if kind == "outside":
        term = torch.relu(-f)
    elif kind == "density":
        term = density(f) * length
    else:
        term = density.occupancy(f) * length
    return (term if weights is None else term * weights).mean()


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


MAX_DEPTH = 13.8
"""The optical depth at which :func:`log_depth` stops (opacity 1 - 1e-6): float32 keeps 1 - opacity there."""


def log_depth(opacity: torch.Tensor) -> torch.Tensor:
    """(R,) ``log(1 + tau)`` of the optical depth ``tau = -log(1 - opacity)`` an opacity stands for.

    A loss on the opacity in front of a ray's end saturates behind an opaque sheet (its gradient in
    the sheet's depth falls as ``1 - opacity``, i.e. ``exp(-tau)``); on ``log(1 + tau)`` it falls as
    ``1 / (1 + tau)`` only. Near 0 both are the opacity to first order.

    Args:
        opacity: (R,) in [0, 1] (e.g. :func:`opacity_before`).
    Returns:
        (R,) >= 0; at opacities above ``1 - exp(-MAX_DEPTH)`` the value of ``MAX_DEPTH`` and no gradient.
    """
    top = 1.0 - math.exp(-MAX_DEPTH)
    return torch.log1p(-torch.log1p(-opacity.clamp(min=0.0, max=top)))


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
