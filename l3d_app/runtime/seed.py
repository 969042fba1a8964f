"""Seeding: one call makes a run reproducible from its config."""

from __future__ import annotations

import random

import numpy as np
import torch


def seed_everything(seed: int, device: torch.device = torch.device("cpu")) -> torch.Generator:
    """Seed Python, NumPy and torch; return the run's one CPU torch.Generator seeded with ``seed``.

    Library code that needs randomness takes this generator explicitly; draws meant for
    another device go through :mod:`l3d_app.runtime.random` (drawn on the CPU, then moved).
    ``device`` is accepted for compatibility and ignored: the generator is always on the CPU.
    """
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)
    gen = torch.Generator(device="cpu")
    gen.manual_seed(seed)
    return gen
