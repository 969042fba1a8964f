"""The training loop's checkpoint: ``checkpoint.pt`` in the run directory, written atomically.

A checkpoint holds the step, the :class:`~l3d_app.runtime.training.Trainable`'s state (modules,
optimiser, schedulers, extra state), the run's RNG state (its generator and torch's global one, so
a resumed CPU run ends like an uninterrupted one) and the loop's history (evaluations, counters).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Dict, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.torch_files import read_torch_file

CHECKPOINT = "checkpoint.pt"


def _rng_state(generator: torch.Generator) -> Dict[str, Any]:
    return {"generator": generator.get_state(), "torch": torch.get_rng_state()}


def _set_rng_state(generator: torch.Generator, state: Dict[str, Any]) -> None:
    generator.set_state(state["generator"])
    torch.set_rng_state(state["torch"])


def save_checkpoint(path: Path, trainable, step: int, generator: torch.Generator, history: Dict[str, Any]) -> bool:
    """Write a checkpoint atomically; refuses (returns False) if any parameter is non-finite."""
    if not trainable.all_finite():
        return False
    state = {"step": step, "trainable": trainable.state_dict(), "rng": _rng_state(generator),
             "history": history}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return True


def read_checkpoint(path: Path) -> Dict[str, Any]:
    """The dict of a ``checkpoint.pt`` written by :func:`save_checkpoint` (on the CPU); a file
    that is not one (empty, truncated, another format, no ``trainable``) is a :class:`UserError`."""
    state = read_torch_file(path, "checkpoint")
    if not isinstance(state, dict) or "trainable" not in state:
        raise UserError(f"{path} is not a checkpoint of this app (no 'trainable' state)")
    return state


def load_checkpoint(path: Path, trainable, generator: torch.Generator) -> Dict[str, Any]:
    """Restore a checkpoint written by :func:`save_checkpoint`; returns its dict. One written by
    another task, or by a model of other sizes, is a :class:`UserError` that says which, before
    anything of the run is touched on disk."""
    state = read_checkpoint(path)
    saved = sorted(state["trainable"].get("modules", {}))
    if saved != sorted(trainable.modules):
        raise UserError(f"{path} holds {', '.join(saved) or 'no modules'}, this run trains "
                        f"{', '.join(sorted(trainable.modules))}: a checkpoint of another task? "
                        "Resume with the task that wrote it, or give this run its own hydra.run.dir")
    try:
        trainable.load_state_dict(state["trainable"])
    except (RuntimeError, ValueError, KeyError) as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        detail = lines[1] if len(lines) > 1 else (lines[0] if lines else type(err).__name__)  # torch: a header, then one line per key
        raise UserError(f"{path} does not fit this run's model ({detail}): "
                        "resume with the settings that wrote it, or give this run its own hydra.run.dir") from err
    _set_rng_state(generator, state["rng"])
    return state


def resume_from(ctx, trainable, resume: bool) -> Tuple[int, Dict[str, Any]]:
    """(the step to start at, the loop's history): from ``checkpoint.pt`` in ``ctx.out_dir`` with
    ``resume`` when it exists (logged), else step 0 and an empty history (with a note when
    ``resume`` found no checkpoint)."""
    path = ctx.out_dir / CHECKPOINT
    if resume and path.exists():
        state = load_checkpoint(path, trainable, ctx.generator)
        ctx.logger.text("train/resume", f"resumed from step {int(state['step'])}")
        return int(state["step"]), state["history"]
    if resume:
        note = f"resume=true, but there is no {path}: training starts at step 0"
        print(f"l3d_app: note: {note}", file=sys.stderr)
        ctx.logger.text("train/resume", note)
    return 0, {"eval": []}
