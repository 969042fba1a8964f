"""Run-time services below every other layer: device, seeding and random draws, the
training loop, checkpoints, logging, progress bars, timers, media and file helpers."""

from l3d_app.exports import lazy_exports
from l3d_app.runtime import optim  # noqa: F401,E402  (registers OPTIMIZERS)

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "RunContext": "context",
    "Trainable": "training",
    "LoopSpec": "training",
    "TimeBudget": "budget",
    "train": "training",
    "log_test": "training",
    "build_optimizer": "optim",
    "resolve_device": "device",
    "seed_everything": "seed",
})
