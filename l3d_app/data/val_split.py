"""A seeded validation split carved from a training split (never from the test split).

Every trained task chooses (best checkpoint, defaults) on validation data and reads its test
split once, at the end. Datasets that ship only train / test (the course's point clouds,
ModelNet40, the built-in generators) carve the validation split from train with
:func:`carve_val`: a fraction of the training items, drawn per class (stratified) so a
small validation split still sees every class, fixed by its own seed.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch

from l3d_app.errors import UserError


def carve_val(n: int, fraction: float, seed: int = 0,
              labels: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Split ``range(n)`` into (train, val) index tensors (int64, sorted).

    Args:
        n: number of training items.
        fraction: share of them that goes to validation, in [0, 1). Per class
            ``round(fraction * count)`` items, at least one when ``fraction`` > 0 and the
            class has two or more items (a class with one item stays in train).
        seed: fixes which items go to validation (independent of any other seed).
        labels: optional (n,) integer class per item; the draw is stratified by it.

    Raises :class:`~l3d_app.errors.UserError` (a ValueError) for a fraction outside [0, 1) or labels of the wrong shape, and when
    nothing would be left to train on.
    """
    fraction = float(fraction)
    if not 0.0 <= fraction < 1.0:
        raise UserError(f"val_fraction must be in [0, 1), got {fraction}")
    if labels is None:
        labels = torch.zeros(n, dtype=torch.long)
    labels = torch.as_tensor(labels).long().reshape(-1)
    if labels.numel() != n:
        raise UserError(f"labels must hold {n} entries, got {labels.numel()}")
    gen = torch.Generator().manual_seed(int(seed))
    order = torch.randperm(n, generator=gen)           # one draw, then taken class by class
    val = []
    if fraction > 0:
        for c in torch.unique(labels).tolist():
            members = order[labels[order] == c]
            count = members.numel()
            k = min(count - 1, max(1, int(math.floor(fraction * count + 0.5)))) if count >= 2 else 0
            val.append(members[:k])
    val_idx = torch.sort(torch.cat(val)).values if val else torch.zeros(0, dtype=torch.long)
    keep = torch.ones(n, dtype=torch.bool)
    keep[val_idx] = False
    train_idx = torch.nonzero(keep)[:, 0]
    if train_idx.numel() == 0:
        raise UserError(f"val_fraction={fraction} leaves no training items out of {n}")
    return train_idx, val_idx
