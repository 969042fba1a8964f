"""The course's training-progress frame: four views rendered now above the same views' ground truth."""

from __future__ import annotations

import torch


def progress_grid(pred: torch.Tensor, truth: torch.Tensor, views: int = 4) -> torch.Tensor:
    """(2H, k W, 3) frame: the first k = min(``views``, V) predictions (V, H, W, 3) left to right in the
    top row, their ground truth (V, H, W, 3) in the bottom row; values clamped to [0, 1], on the CPU."""
    k = max(1, min(int(views), pred.shape[0]))
    top = torch.cat(list(pred[:k].detach().float().cpu().clamp(0, 1)), dim=1)
    bottom = torch.cat(list(truth[:k].detach().float().cpu().clamp(0, 1)), dim=1)
    return torch.cat([top, bottom], dim=0)
