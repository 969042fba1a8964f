"""F1 at many distance thresholds from one nearest-neighbour pass, and its mean over objects.

Same definition as :func:`l3d_app.metrics.fscore.fscore` (precision: share of predicted
points within the threshold of the target; recall: the converse; a distance equal to the
threshold counts), which searches again for every threshold; here the nearest distances
are found once and every threshold reads them.
"""

from __future__ import annotations

from typing import Any, Dict, Sequence, Tuple

import numpy as np
import torch

from l3d_app.metrics.chamfer import nearest_neighbors_both


@torch.no_grad()
def f1_curve(pred: torch.Tensor, target: torch.Tensor, thresholds: Sequence[float]) -> Tuple[np.ndarray, float]:
    """F1 of ``pred`` (N, 3) vs ``target`` (M, 3) at every threshold (world units), (T,)
    float64, and the chamfer distance (sum of the two mean SQUARED nearest distances)."""
    idx_pt, idx_tp = nearest_neighbors_both(pred, target, chunk_size=int(pred.shape[0]))
    d_pt = (pred - target[idx_pt]).norm(dim=-1)
    d_tp = (target - pred[idx_tp]).norm(dim=-1)
    th = torch.tensor([float(t) for t in thresholds], dtype=d_pt.dtype, device=d_pt.device)
    p = (d_pt[None] <= th[:, None]).double().mean(1)
    r = (d_tp[None] <= th[:, None]).double().mean(1)
    f1 = torch.where(p + r > 0, 2 * p * r / (p + r).clamp_min(1e-300), torch.zeros_like(p))
    return f1.cpu().numpy(), float(d_pt.square().mean() + d_tp.square().mean())


def f1_table(preds: Sequence[torch.Tensor], targets: Sequence[torch.Tensor], thresholds: Sequence[float]
             ) -> Dict[str, Any]:
    """Mean over objects of F1 at each threshold (an empty prediction scores 0) and the mean
    chamfer of the non-empty ones (None if all are empty).
    Returns {"f1": (T,) array, "chamfer": float or None, "empty": int}."""
    f1 = np.zeros((len(preds), len(thresholds)))
    chamfers, empty = [], 0
    for i, (p, t) in enumerate(zip(preds, targets)):
        if p.shape[0] == 0:
            empty += 1
            continue
        f1[i], ch = f1_curve(p, t, thresholds)
        chamfers.append(ch)
    return {"f1": f1.mean(0), "chamfer": float(np.mean(chamfers)) if chamfers else None, "empty": empty}


def threshold_key(t: float) -> str:
    """metrics.json key of F1 at threshold ``t``: ``f1@0.05``."""
    return f"f1@{float(t):g}"
