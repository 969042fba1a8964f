"""Random draws from the run's one CPU generator, placed on the compute device.

Every run has one seeded ``torch.Generator`` on the CPU (``ctx.generator``). Draws are made
on the CPU with it and then moved, so a run gives the same numbers on any device and a
checkpoint's RNG state is one CPU state. Use these helpers instead of passing
``device=`` to ``torch.rand*`` (which would need a generator on that device).
"""

from __future__ import annotations

from typing import Sequence, Union

import torch

Device = Union[str, torch.device, None]


def rand(shape: Sequence[int], generator: torch.Generator, device: Device = None,
         dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Uniform [0, 1) samples of ``shape`` on ``device``."""
    return torch.rand(tuple(shape), generator=generator, dtype=dtype).to(device or "cpu")


def randn(shape: Sequence[int], generator: torch.Generator, device: Device = None,
          dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Standard normal samples of ``shape`` on ``device``."""
    return torch.randn(tuple(shape), generator=generator, dtype=dtype).to(device or "cpu")


def randint(low: int, high: int, shape: Sequence[int], generator: torch.Generator,
            device: Device = None) -> torch.Tensor:
    """Integers in [low, high) of ``shape`` (int64) on ``device``."""
    return torch.randint(int(low), int(high), tuple(shape), generator=generator).to(device or "cpu")


def randperm(n: int, generator: torch.Generator, device: Device = None) -> torch.Tensor:
    """A random permutation of ``range(n)`` (int64) on ``device``."""
    return torch.randperm(int(n), generator=generator).to(device or "cpu")
