"""Classification metrics: accuracy, confusion matrices, per-class accuracy and IoU (integer labels)."""

from __future__ import annotations

from typing import Dict, Sequence

import numpy as np
import torch


def accuracy(pred: torch.Tensor, target: torch.Tensor) -> float:
    """Fraction of equal entries of two integer tensors of the same shape (nan if empty)."""
    if pred.shape != target.shape:
        raise ValueError(f"shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    return float((pred == target).float().mean()) if pred.numel() else float("nan")


def confusion_matrix(pred: torch.Tensor, target: torch.Tensor, num_classes: int) -> torch.Tensor:
    """(K, K) int64 counts: row = true class, column = predicted class (any input shape)."""
    idx = target.reshape(-1).long() * num_classes + pred.reshape(-1).long()
    return torch.bincount(idx, minlength=num_classes * num_classes).view(num_classes, num_classes)


def per_label_accuracy(pred: torch.Tensor, target: torch.Tensor, names: Sequence[str], kind: str) -> Dict[str, float]:
    """Accuracy per true class, ``accuracy_<name>`` (``kind`` 'cls'), or IoU per part, ``iou_<name>``,
    and their mean ``miou`` (``kind`` 'seg'), of integer labels ``pred`` and ``target``."""
    out = {}
    k = len(names)
    cm = confusion_matrix(pred, target, k).double()
    if kind == "cls":
        for c in range(k):
            if cm[c].sum() > 0:
                out[f"accuracy_{names[c]}"] = float(cm[c, c] / cm[c].sum())
    else:
        ious = []
        for c in range(k):
            union = cm[c].sum() + cm[:, c].sum() - cm[c, c]
            if union > 0:
                ious.append(float(cm[c, c] / union))
                out[f"iou_{names[c].replace('/', '_')}"] = ious[-1]
        out["miou"] = float(np.mean(ious)) if ious else float("nan")
    return out
