"""Occupancy grid for empty-space skipping (Instant-NGP / nerfacc style, pure PyTorch).

A coarse ``R^3`` grid of cells over the scene box keeps an exponential moving maximum of the
field's density per cell and marks a cell occupied when that value exceeds a threshold:

* ``update(density_fn, step)``: every ``update_every`` steps, the density at one random
  point in every cell gives ``ema = max(decay * ema, sigma)``; cells with
  ``ema > min(threshold, mean(ema))`` are occupied (the mean keeps an untrained field from
  being culled entirely). During the first ``warmup_steps`` steps every cell stays occupied.
* ``occupied(points)``: which of (N, 3) points lie in an occupied cell (outside the box: no).

The grid is the scene's own picture of where matter is; its occupied fraction is reported
next to the error figures. State (ema, mask) lives in buffers, so it checkpoints with
``state_dict``.
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError


class OccupancyGrid(torch.nn.Module):
    """Binary occupancy over an axis-aligned box.

    Args:
        scene_box: ((x0, y0, z0), (x1, y1, z1)) world box.
        resolution: cells per axis R.
        threshold: density (1 / world units) above which a cell is occupied; e.g. an alpha of
            1% over a step ``dt`` is ``-log(0.99) / dt``.
        decay: EMA decay of the per-cell max density, per update.
        warmup_steps: steps during which every cell is occupied.
        update_every: steps between updates.
        chunk: points per density call during an update.
    """

    def __init__(self, scene_box: Tuple[Sequence[float], Sequence[float]], resolution: int = 64,
                 threshold: float = 0.5, decay: float = 0.95, warmup_steps: int = 256,
                 update_every: int = 16, chunk: int = 65536):
        super().__init__()
        if resolution < 1 or update_every < 1 or not 0.0 <= decay <= 1.0:
            raise UserError(f"occupancy grid needs resolution >= 1, update_every >= 1 and decay in [0, 1], "
                            f"got {resolution}, {update_every}, {decay}")
        lo = torch.as_tensor(scene_box[0], dtype=torch.float32).reshape(3)
        hi = torch.as_tensor(scene_box[1], dtype=torch.float32).reshape(3)
        self.register_buffer("lo", lo)
        self.register_buffer("hi", hi)
        self.resolution, self.threshold, self.decay = int(resolution), float(threshold), float(decay)
        self.warmup_steps, self.update_every, self.chunk = int(warmup_steps), int(update_every), int(chunk)
        n = self.resolution ** 3
        self.register_buffer("density_ema", torch.zeros(n))
        self.register_buffer("mask", torch.ones(n, dtype=torch.bool))

    @property
    def occupied_fraction(self) -> float:
        """Fraction of cells marked occupied, in [0, 1]."""
        return float(self.mask.float().mean())

    def cell_index(self, points: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Flat cell ids (N,) long (``i R^2 + j R + k``) and inside-box flags (N,) for points (N, 3)."""
        u = (points - self.lo.to(points.dtype)) / (self.hi - self.lo).to(points.dtype)
        inside = ((u >= 0) & (u <= 1)).all(dim=-1)
        ijk = (u * self.resolution).long().clamp(0, self.resolution - 1)
        r = self.resolution
        return ijk[..., 0] * (r * r) + ijk[..., 1] * r + ijk[..., 2], inside

    def occupied(self, points: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the point lies inside the box in an occupied cell."""
        idx, inside = self.cell_index(points)
        return inside & self.mask[idx]

    def cell_centers(self) -> torch.Tensor:
        """(R^3, 3) world centres of the cells, in flat-id order."""
        r = self.resolution
        ax = (torch.arange(r, dtype=torch.float32, device=self.lo.device) + 0.5) / r
        g = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), dim=-1).reshape(-1, 3)
        return self.lo + g * (self.hi - self.lo)

    @torch.no_grad()
    def update(self, density_fn: Callable[[torch.Tensor], torch.Tensor], step: int,
               generator: Optional[torch.Generator] = None, force: bool = False) -> bool:
        """Refresh the grid from ``density_fn(points (N, 3)) -> (N,)`` if ``step`` is due.

        Returns True when an update happened.
        """
        if not force and (step + 1) % self.update_every != 0:
            return False
        cell = (self.hi - self.lo) / self.resolution
        centres = self.cell_centers()
        jitter = torch.rand(centres.shape, generator=generator).to(centres.device)   # CPU draw, then moved
        pts = centres + (jitter - 0.5) * cell
        sigma = torch.cat([density_fn(pts[s:s + self.chunk]).reshape(-1).float()
                           for s in range(0, pts.shape[0], self.chunk)])
        self.density_ema.copy_(torch.maximum(self.density_ema * self.decay, sigma))
        if step + 1 < self.warmup_steps and not force:
            self.mask.fill_(True)
        else:
            thr = min(self.threshold, float(self.density_ema.mean()))
            self.mask.copy_(self.density_ema > thr)
        return True
