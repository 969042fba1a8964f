"""Point clouds: positions with optional per-point colours and normals."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Optional

import torch

from l3d_app.errors import UserError


@dataclass
class PointCloud:
    """A single point cloud.

    Attributes:
        points: (N, 3) float positions (world units).
        colors: optional (N, 3) RGB in [0, 1].
        normals: optional (N, 3) unit normals.
    """

    points: torch.Tensor
    colors: Optional[torch.Tensor] = None
    normals: Optional[torch.Tensor] = None

    def __post_init__(self):
        p = self.points
        if p.dim() != 2 or p.shape[-1] != 3:
            raise UserError(f"point cloud must be (N, 3), got {tuple(p.shape)}")
        if not torch.isfinite(p).all():
            raise UserError("point cloud contains NaN or Inf")
        for name in ("colors", "normals"):
            value = getattr(self, name)
            if value is not None and value.shape != p.shape:
                raise UserError(f"point cloud {name} must be {tuple(p.shape)}, got {tuple(value.shape)}")

    @property
    def num_points(self) -> int:
        return self.points.shape[0]

    @property
    def device(self) -> torch.device:
        return self.points.device

    def to(self, device=None, dtype=None) -> "PointCloud":
        out = {}
        for fld in fields(self):
            value = getattr(self, fld.name)
            out[fld.name] = value.to(device=device, dtype=dtype) if torch.is_tensor(value) else value
        return PointCloud(**out)

    def normalized(self, radius: float = 1.0) -> "PointCloud":
        """Centred at the bounding-box centre, farthest point at ``radius``."""
        lo, hi = self.points.min(0).values, self.points.max(0).values
        centred = self.points - (lo + hi) / 2
        scale = radius / centred.norm(dim=-1).max().clamp_min(1e-12)
        return PointCloud(centred * scale, self.colors, self.normals)
