"""Data-parallel training when launched by ``torchrun`` (single process otherwise).

``torchrun --nproc_per_node=2 main.py task=pointnet_cls`` sets ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT``; :func:`setup` then joins the process
group (gloo on CPU, NCCL on CUDA, each rank on ``cuda:LOCAL_RANK``). Without those
variables everything is a no-op with rank 0 of a world of 1.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass
class Dist:
    """Where this process stands: ``rank`` of ``world`` processes (``world == 1``: single)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    initialised_here: bool = False

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def launched() -> bool:
    """True when the environment describes a multi-process launch (torchrun)."""
    return "RANK" in os.environ and int(os.environ.get("WORLD_SIZE", "1")) > 1


def setup(device: torch.device) -> Dist:
    """Join the process group if launched by torchrun (or reuse an existing one)."""
    if dist.is_available() and dist.is_initialized():
        return Dist(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", 0)))
    if not launched() or not dist.is_available():
        return Dist()
    backend = "nccl" if device.type == "cuda" else "gloo"
    local = int(os.environ.get("LOCAL_RANK", os.environ["RANK"]))
    if device.type == "cuda":
        torch.cuda.set_device(local)
    dist.init_process_group(backend=backend)
    return Dist(dist.get_rank(), dist.get_world_size(), local, initialised_here=True)


def device_for(state: Dist, device: torch.device) -> torch.device:
    """This rank's device: ``cuda:LOCAL_RANK`` for CUDA runs, the given device otherwise."""
    if state.enabled and device.type == "cuda":
        return torch.device("cuda", state.local_rank)
    return device


def teardown(state: Dist) -> None:
    """Leave the process group if :func:`setup` joined it."""
    if state.initialised_here and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def wrap(model: torch.nn.Module, state: Dist, device: torch.device) -> torch.nn.Module:
    """``DistributedDataParallel(model)`` when distributed, the model itself otherwise."""
    if not state.enabled:
        return model
    from torch.nn.parallel import DistributedDataParallel

    ids = [device.index] if device.type == "cuda" else None
    return DistributedDataParallel(model, device_ids=ids)
