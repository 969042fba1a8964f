"""A single-view scan of a point set: which surface samples a scanner looking along one direction sees.

Orthographic visibility by a point z-buffer (vectorised): the points are projected onto the plane
perpendicular to the viewing direction ``d`` (unit), binned into a ``grid`` x ``grid`` raster over
``[-extent, extent]^2``, and a point is visible when its depth ``p . d`` is within ``tolerance`` of the
nearest depth in its cell (the scanner's depth resolution). Dense surface samples in, the samples of
the front-facing surface out: the back of an object, a cavity's far wall and what one part hides of
another are missing, as in a real single-view scan.
"""

from __future__ import annotations

import math
from typing import Tuple

import torch


def view_direction(azimuth_deg: float, elevation_deg: float) -> torch.Tensor:
    """(3,) unit direction a scanner looks along, from a viewpoint at ``azimuth_deg`` about +Y (from +Z
    towards +X) and ``elevation_deg`` above the XZ plane, looking at the origin."""
    a, e = math.radians(float(azimuth_deg)), math.radians(float(elevation_deg))
    eye = torch.tensor([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])
    return -eye


def image_plane_basis(direction: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors (3,) spanning the plane perpendicular to ``direction`` (3,)."""
    d = direction / direction.norm()
    helper = torch.tensor([0.0, 1.0, 0.0], dtype=d.dtype) if float(d[1].abs()) < 0.9 else \
        torch.tensor([1.0, 0.0, 0.0], dtype=d.dtype)
    u = torch.linalg.cross(helper, d)
    u = u / u.norm()
    return u, torch.linalg.cross(d, u)


def visible_points(points: torch.Tensor, direction: torch.Tensor, grid: int = 64, extent: float = 1.0,
                   tolerance: float = 0.02) -> torch.Tensor:
    """(N,) bool: the points (N, 3) (world units, inside ``extent`` of the origin across the view) that a
    scanner looking along ``direction`` (3,) sees (see the module docstring)."""
    d = (direction / direction.norm()).to(points)
    u, v = image_plane_basis(d)
    ij = ((torch.stack([points @ u, points @ v], -1) + extent) / (2 * extent) * grid).floor().long()
    ij = ij.clamp(0, int(grid) - 1)
    cell = ij[:, 0] * int(grid) + ij[:, 1]
    depth = points @ d
    nearest = torch.full((int(grid) ** 2,), float("inf"), dtype=points.dtype)
    nearest = nearest.scatter_reduce(0, cell, depth, reduce="amin")
    return depth <= nearest[cell] + float(tolerance)
