"""Intersection over union of occupancy grids."""

from __future__ import annotations

import torch

from l3d_app.errors import UserError


def iou(pred: torch.Tensor, target: torch.Tensor) -> float:
    """``|pred & target| / |pred | target|`` of two boolean occupancy grids of one shape.

    Any shape ((R, R, R) grids, batches); non-bool inputs count as occupied where > 0.5.
    Two empty grids agree perfectly: 1.0.
    """
    if pred.shape != target.shape:
        raise UserError(f"iou: shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    p = pred if pred.dtype == torch.bool else pred > 0.5
    t = target if target.dtype == torch.bool else target > 0.5
    union = int((p | t).sum())
    return 1.0 if union == 0 else int((p & t).sum()) / union
