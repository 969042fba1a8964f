"""Occupancy losses: binary cross-entropy on LOGITS (stable for saturated predictions)."""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from l3d_app.registry import LOSSES


def bce_with_logits(logits: torch.Tensor, target: torch.Tensor, pos_weight: Optional[float] = None,
                    reduction: str = "mean") -> torch.Tensor:
    """Binary cross-entropy of occupancy ``logits`` (...) against ``target`` (...) in [0, 1].

    Computed as ``max(z, 0) - z t + log(1 + exp(-|z|))`` (PyTorch's fused kernel), never via
    ``sigmoid`` then ``log``: finite for any finite logit (|z| = 1e4 included), with the exact
    gradient ``sigmoid(z) - t`` (times ``pos_weight`` on the positive term when given).
    Units: nats per element (``reduction`` "mean" | "sum" | "none").
    """
    pw = None if pos_weight is None else logits.new_tensor(float(pos_weight))
    return F.binary_cross_entropy_with_logits(logits, target.to(logits.dtype), pos_weight=pw,
                                              reduction=reduction)


@LOSSES.register("bce_logits")
class BCEWithLogits:
    """``loss(logits, target)``: :func:`bce_with_logits` with fixed ``pos_weight``/``reduction``."""

    def __init__(self, pos_weight: Optional[float] = None, reduction: str = "mean"):
        self.pos_weight, self.reduction = pos_weight, reduction

    def __call__(self, logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return bce_with_logits(logits, target, self.pos_weight, self.reduction)
