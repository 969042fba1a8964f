"""A radiance field started from a soft ball (DreamFusion's density blob)."""

from __future__ import annotations

import torch

from l3d_app.errors import UserError


class BlobField(torch.nn.Module):
    """``field`` with its density multiplied by ``exp(blob_density * exp(-|x|^2 / (2 r^2)))``.

    ``forward(points (N, 3), dirs (N, 3)) -> (sigma (N,), rgb (N, 3))`` like the wrapped field.
    """

    def __init__(self, field: torch.nn.Module, blob_density: float = 5.0, blob_radius: float = 0.5):
        super().__init__()
        if blob_radius <= 0:
            raise UserError(f"blob_radius must be > 0, got {blob_radius}")
        self.field, self.blob_density, self.blob_radius = field, float(blob_density), float(blob_radius)

    def blob(self, points: torch.Tensor) -> torch.Tensor:
        return self.blob_density * torch.exp(-(points * points).sum(-1) / (2 * self.blob_radius ** 2))

    def density(self, points: torch.Tensor) -> torch.Tensor:
        return self.field.density(points) * torch.exp(self.blob(points))

    def forward(self, points: torch.Tensor, dirs: torch.Tensor):
        sigma, rgb = self.field(points, dirs)
        return sigma * torch.exp(self.blob(points)), rgb
