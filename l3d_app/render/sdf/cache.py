"""A trilinear grid copy of an SDF: a cheap stand-in for the field in a coarse sampling pass."""

from __future__ import annotations

from typing import Callable, Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError

SdfFn = Callable[[torch.Tensor], torch.Tensor]


class SDFGridCache(torch.nn.Module):
    """A trilinear ``R^3`` copy of an SDF over a box: a cheap stand-in for the coarse pass.

    ``update(sdf_fn)`` evaluates the SDF (no grad) at the ``R^3`` vertices of
    :func:`~l3d_app.geometry.marching_cubes.grid_points` over ``box``; ``cache(points (..., 3))``
    interpolates them trilinearly (``grid_sample``, ``align_corners=True``; points outside the
    box take the nearest border value). A look-up costs a few ns where a field evaluation
    costs microseconds, so the coarse pass can afford many samples per ray. The values are
    as stale as the last update (the task refreshes it every ``every`` steps); they only
    place samples, the rendered SDF is always the field's own.
    """

    def __init__(self, box: Tuple[Sequence[float], Sequence[float]], resolution: int = 64):
        super().__init__()
        if int(resolution) < 2:
            raise UserError(f"SDF cache resolution must be >= 2, got {resolution}")
        self.resolution = int(resolution)
        self.register_buffer("lo", torch.as_tensor(box[0], dtype=torch.float32).reshape(3))
        self.register_buffer("hi", torch.as_tensor(box[1], dtype=torch.float32).reshape(3))
        self.register_buffer("values", torch.zeros(self.resolution, self.resolution, self.resolution))

    @property
    def cell_size(self) -> float:
        """The largest spacing of the grid's vertices along an axis (world units)."""
        return float(((self.hi - self.lo) / (self.resolution - 1)).max())

    @torch.no_grad()
    def update(self, sdf_fn: SdfFn, chunk_size: Optional[int] = None) -> None:
        from l3d_app.geometry.marching_cubes import evaluate_grid

        self.values.copy_(evaluate_grid(sdf_fn, self.lo.tolist(), self.hi.tolist(), self.resolution,
                                        chunk_size=chunk_size, device=self.values.device))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """points (..., 3) world -> (...) interpolated SDF."""
        u = (points.reshape(-1, 3) - self.lo) / (self.hi - self.lo) * 2.0 - 1.0     # [-1, 1] per axis
        # grid_sample's (x, y, z) index (W, H, D) = values[D=i, H=j, W=k]: reverse the axes
        g = u.flip(-1).reshape(1, -1, 1, 1, 3).to(self.values.dtype)
        out = torch.nn.functional.grid_sample(self.values[None, None], g, mode="bilinear",
                                              padding_mode="border", align_corners=True)
        return out.reshape(points.shape[:-1]).to(points.dtype)


