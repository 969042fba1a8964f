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


def coverage_bce(optical_depth: torch.Tensor, coverage: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Mean binary cross-entropy of each ray's opacity ``1 - exp(-tau)`` against the image's
    coverage (alpha) ``m`` in [0, 1], written in the optical depth ``tau`` (R,) >= 0 (nats):

        -m log(1 - exp(-(tau + eps))) + (1 - m) tau

    The negative term is ``-log(exp(-tau)) = tau`` exactly, so a ray that should see nothing
    gets gradient ``1 - m`` however opaque it is (the opacity itself saturates to 1 in float32
    once tau > 17, and a BCE on it would have no gradient there). ``eps`` (nats) keeps the
    positive term finite at tau = 0 (its largest value is ``-log(1 - exp(-eps))`` ~ 6.9).
    """
    tau = optical_depth.clamp_min(0.0)
    m = coverage.to(tau.dtype)
    return (-m * torch.log(-torch.expm1(-(tau + eps))) + (1.0 - m) * tau).mean()


@LOSSES.register("bce_logits")
class BCEWithLogits:
    """``loss(logits, target)``: :func:`bce_with_logits` with fixed ``pos_weight``/``reduction``."""

    def __init__(self, pos_weight: Optional[float] = None, reduction: str = "mean"):
        self.pos_weight, self.reduction = pos_weight, reduction

    def __call__(self, logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return bce_with_logits(logits, target, self.pos_weight, self.reduction)
