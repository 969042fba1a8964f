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

``occupied_fraction(f, softness) = mean(sigmoid(-f / softness))``: the share of the box inside
the solid, smoothed over ``softness`` world units; its gradient sits at the boundary
(``|f|`` within a few ``softness``) and leaves the inside's values alone.
"""

from __future__ import annotations

import torch


def occupied_volume(sdf: torch.Tensor) -> torch.Tensor:
    """Scalar ``mean(max(0, -sdf))`` of SDF values (world units) at uniform box points."""
    return torch.relu(-sdf).mean()


def occupied_fraction(sdf: torch.Tensor, softness: float) -> torch.Tensor:
    """Scalar ``mean(sigmoid(-sdf / softness))`` (unitless, in [0, 1]) of SDF values at uniform box
    points; ``softness`` > 0 in world units."""
    if not float(softness) > 0:
        raise ValueError(f"softness must be > 0, got {softness}")
    return torch.sigmoid(-sdf / float(softness)).mean()
