"""Seeding: one call makes a run reproducible from its config."""

from __future__ import annotations

import random

import numpy as np
import torch


def seed_everything(seed: int, device: torch.device = torch.device("cpu")) -> torch.Generator:
    """Seed Python, NumPy and torch; return a torch.Generator on ``device`` seeded with ``seed``.

    Library code that needs randomness takes this generator explicitly.
    """
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)
    gen = torch.Generator(device=device)
    gen.manual_seed(seed)
    return gen
