"""Which way surfaces face: horizontal / vertical classification of normals, sign-free normal
errors and the summary statistics of a point cloud.

PCA normals have no sign, so everything here treats ``n`` and ``-n`` alike.
"""

from __future__ import annotations

import math
from typing import Dict, Sequence

import torch

from l3d_app.errors import UserError

HORIZONTAL, VERTICAL, OTHER = 0, 1, 2
CLASS_NAMES = ("horizontal", "vertical", "other")


def classify_orientation(normals: torch.Tensor, up: Sequence[float] = (0.0, 1.0, 0.0),
                         tolerance_deg: float = 15.0) -> torch.Tensor:
    """(N,) long class of each surface from its normal (N, 3):

    - ``HORIZONTAL`` (0), e.g. a floor: the normal's line is within ``tolerance_deg`` of ``up``,
      ``|n . up| >= cos(tol)``;
    - ``VERTICAL`` (1), e.g. a wall: the normal is within ``tolerance_deg`` of perpendicular to
      ``up``, ``|n . up| <= sin(tol)``;
    - ``OTHER`` (2): neither (slanted or curved surfaces).
    """
    if not 0 < float(tolerance_deg) < 45:
        raise UserError(f"tolerance_deg must be in (0, 45), got {tolerance_deg}")
    u = torch.as_tensor(up, dtype=normals.dtype, device=normals.device)
    u = u / u.norm()
    c = (torch.nn.functional.normalize(normals, dim=-1) @ u).abs()
    tol = math.radians(float(tolerance_deg))
    out = torch.full(c.shape, OTHER, dtype=torch.long, device=normals.device)
    out[c >= math.cos(tol)] = HORIZONTAL
    out[c <= math.sin(tol)] = VERTICAL
    return out


def classify_by_cosine(normals: torch.Tensor, up: Sequence[float] = (0.0, 1.0, 0.0), horizontal_above: float = 0.8,
                       vertical_below: float = 0.3) -> torch.Tensor:
    """(N,) long class of each normal (N, 3) by ``c = |n . up|`` of the unit normal (the worked exercise's
    rule, ``|n_y|`` for ``up = y``): ``HORIZONTAL`` where ``c > horizontal_above``, ``VERTICAL`` where
    ``c < vertical_below``, ``OTHER`` otherwise (needs ``0 <= vertical_below <= horizontal_above <= 1``)."""
    if not 0.0 <= float(vertical_below) <= float(horizontal_above) <= 1.0:
        raise UserError(f"need 0 <= vertical_below <= horizontal_above <= 1, got {vertical_below}, {horizontal_above}")
    u = torch.as_tensor(up, dtype=normals.dtype, device=normals.device)
    c = (torch.nn.functional.normalize(normals, dim=-1) @ (u / u.norm())).abs()
    out = torch.full(c.shape, OTHER, dtype=torch.long, device=normals.device)
    out[c > float(horizontal_above)] = HORIZONTAL
    out[c < float(vertical_below)] = VERTICAL
    return out


def unsigned_angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N,) angle in degrees, in [0, 90], between the LINES of normals a and b (N, 3)."""
    cos = (torch.nn.functional.normalize(a, dim=-1) * torch.nn.functional.normalize(b, dim=-1)).sum(-1).abs()
    return torch.rad2deg(torch.acos(cos.clamp(max=1.0)))


def point_statistics(points: torch.Tensor) -> Dict[str, list]:
    """count, bounds (per-axis min and max) and centroid (mean) of (N, 3) points, as plain lists."""
    return {"count": int(points.shape[0]), "bounds_min": points.min(0).values.tolist(),
            "bounds_max": points.max(0).values.tolist(), "centroid": points.mean(0).tolist()}
