"""Random draws from the run's one CPU generator, placed on the compute device.

Every run has one seeded ``torch.Generator`` on the CPU (``ctx.generator``). Draws are made
on the generator's own device (the CPU for the run's one) and then moved, so a run gives the
same numbers on any device and a checkpoint's RNG state is one CPU state. Use these helpers
instead of passing ``device=`` to ``torch.rand*``: torch refuses a CPU generator for a draw
on CUDA (found by ``bench/device_smoke.py`` on a GPU). ``generator=None`` draws from torch's
global generator on ``device``.
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import torch

Device = Union[str, torch.device, None]


def draw_device(generator: Optional[torch.Generator], device: Device) -> Device:
    """The device a draw is made on: the generator's own, else the target device (for draws
    these helpers do not cover, e.g. ``torch.multinomial``)."""
    return generator.device if generator is not None else (device or "cpu")


def rand(shape: Sequence[int], generator: Optional[torch.Generator], device: Device = None,
         dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Uniform [0, 1) samples of ``shape`` on ``device``."""
    return torch.rand(tuple(shape), generator=generator, dtype=dtype, device=draw_device(generator, device)).to(device or "cpu")


def randn(shape: Sequence[int], generator: Optional[torch.Generator], device: Device = None,
          dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Standard normal samples of ``shape`` on ``device``."""
    return torch.randn(tuple(shape), generator=generator, dtype=dtype, device=draw_device(generator, device)).to(device or "cpu")


def randint(low: int, high: int, shape: Sequence[int], generator: Optional[torch.Generator],
            device: Device = None) -> torch.Tensor:
    """Integers in [low, high) of ``shape`` (int64) on ``device``."""
    return torch.randint(int(low), int(high), tuple(shape), generator=generator,
                         device=draw_device(generator, device)).to(device or "cpu")


def randperm(n: int, generator: Optional[torch.Generator], device: Device = None) -> torch.Tensor:
    """A random permutation of ``range(n)`` (int64) on ``device``."""
    return torch.randperm(int(n), generator=generator, device=draw_device(generator, device)).to(device or "cpu")


HELD_OUT_STREAMS = 1000     # seeds apart: a run's held-out streams never meet another seed's


def held_out_seed(seed: int, offset: int, split: str, stream: int = 0) -> int:
    """The seed of a held-out sample stream: ``seed * 1000 + offset + 2 * stream`` (+ 1 for
    ``split="val"``). Val and test streams never share a seed, neither within a run nor across
    run seeds (an odd and an even number apart; streams < 500), so a setting chosen on one seed's
    val samples is not reported on another seed's identical test samples."""
    if split not in ("val", "test"):
        raise ValueError(f"split must be 'val' or 'test', not {split!r}")
    if not 0 <= int(stream) < HELD_OUT_STREAMS // 2:
        raise ValueError(f"stream must lie in [0, {HELD_OUT_STREAMS // 2}), got {stream}")
    return int(seed) * HELD_OUT_STREAMS + int(offset) + 2 * int(stream) + (1 if split == "val" else 0)
