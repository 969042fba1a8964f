"""Loss terms on a render against the training pixels: colour MSE and the images' coverage (alpha)."""

from __future__ import annotations

from typing import Optional

import torch

from l3d_app.losses.occupancy import coverage_bce
from l3d_app.losses.terms import Batch, LossTerm
from l3d_app.registry import LOSS_TERMS


@LOSS_TERMS.register("color")
class ColorLoss(LossTerm):
    """Mean squared error of the rendered colours against the pixels' (per channel, colours in [0, 1])."""

    def __call__(self, batch: Batch) -> torch.Tensor:
        return ((batch.out["color"] - batch.target) ** 2).mean()


@LOSS_TERMS.register("mask_bce")
class MaskLoss(LossTerm):
    """:func:`~l3d_app.losses.occupancy.coverage_bce` of each ray's optical depth against its pixel's alpha
    (nats per ray); off where the data has no alpha (RGB captures)."""

    def __init__(self, weight: float = 0.1, start: float = 0.0, until: Optional[float] = None):
        super().__init__(weight, start, until)

    def setup(self, state) -> bool:
        return state.rays.mask is not None

    def __call__(self, batch: Batch) -> torch.Tensor:
        return coverage_bce(batch.out["optical_depth"], batch.state.rays.mask[batch.rays])
