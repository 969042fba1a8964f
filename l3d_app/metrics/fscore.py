"""F-score at a distance threshold between point sets (Tatarchenko et al. 2019)."""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.metrics.chamfer import nearest_neighbors_both


@torch.no_grad()
def fscore(pred: torch.Tensor, target: torch.Tensor, threshold: float = 0.05) -> Dict[str, float]:
    """Precision, recall and F1 at ``threshold`` (world units) of ``pred`` (N, 3) vs ``target`` (M, 3).

    precision: fraction of predicted points within ``threshold`` of the target set;
    recall: fraction of target points within ``threshold`` of the prediction;
    f1 = 2 p r / (p + r) (0 when both are 0). A distance equal to the threshold counts.
    Nearest neighbours come from the chamfer's exact search (one pass, both directions).
    """
    idx_pt, idx_tp = nearest_neighbors_both(pred, target)
    d_pt = (pred - target[idx_pt]).norm(dim=-1)
    d_tp = (target - pred[idx_tp]).norm(dim=-1)
    p = float((d_pt <= threshold).float().mean())
    r = float((d_tp <= threshold).float().mean())
    f1 = 0.0 if p + r == 0 else 2 * p * r / (p + r)
    return {"f1": f1, "precision": p, "recall": r}
