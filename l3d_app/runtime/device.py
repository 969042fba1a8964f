"""Device choice: ``auto`` is CUDA when present, else CPU."""

from __future__ import annotations

from typing import Optional

import torch

from l3d_app.errors import UserError


def resolve_device(name: str = "auto") -> torch.device:
    """'auto' | 'cpu' | 'cuda' | 'cuda:N' -> torch.device; an unavailable CUDA is a UserError."""
    name = str(name).lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise UserError(f"device={name} requested but CUDA is not available; use device=auto or device=cpu")
        return torch.device(name)
    raise UserError(f"unknown device '{name}': use auto, cpu or cuda")


def available_host_memory() -> Optional[int]:
    """Bytes of host memory the kernel can give now (Linux ``/proc/meminfo`` MemAvailable), or None
    where that is not known (another OS, an unreadable file)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024       # kB
    except (OSError, ValueError, IndexError):
        return None
    return None
