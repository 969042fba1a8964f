"""Stages: a method's work besides its loss, before and around the training loop (registry ``STAGES``).

A stage is an object composed from config (``stages.<key>: {name: <registered name>, ...}``), like
gsplat's strategies: it owns its knobs and its schedule and is called at fixed points of a run:

- :meth:`Stage.setup`: once, right after the model is built, before anything is rendered (an
  initialisation of the model: :class:`~l3d_app.stages.sphere_init.SphereInit`);
- :meth:`Stage.before_training`: once, just before the first step, with the run's time budget
  (:class:`~l3d_app.runtime.budget.TimeBudget`: its ``stage_deadline`` says until when a stage may run; a fit
  whose result the loss terms read from ``state.products``:
  :class:`~l3d_app.stages.free_space.FreeSpaceStage`);
- :meth:`Stage.on_step`: at each step, before the forward pass (a schedule of the model:
  :class:`~l3d_app.stages.coarse_to_fine.CoarseToFine`);
- :meth:`Stage.metrics`: what it reports in metrics.json.

:class:`MethodState` is what a method's stages and loss terms share. A new stage is a file, a register
line and a yaml (docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Mapping, Optional, Sequence, Set, Tuple

import torch

from l3d_app.geometry.training_rays import TrainingRays
from l3d_app.registry import STAGES
from l3d_app.runtime.budget import TimeBudget

@dataclass
class MethodState:
    """What a method's stages and loss terms share during one run.

    Attributes:
        data: the dataset (``cameras``, ``images``, ``masks``, ``train`` / ``val`` / ``test``, ``scene_box``).
        rays: the training views' rays (:class:`~l3d_app.geometry.training_rays.TrainingRays`).
        model: the trained model; density: its ``DENSITIES`` module.
        box: the scene box ((x0, y0, z0), (x1, y1, z1)), world units.
        iters: the run's steps.
        resuming: the run continues from its checkpoint (stages that wrote files read them back).
        needed: the stage products some weighted loss term reads (a stage that makes none of them is skipped).
        background: makes a fresh background parameter (one RGB behind the box) for a stage's own field.
        products: what the stages made for the loss terms, by name (e.g. ``free_rays``).
    """

    data: Any
    rays: TrainingRays
    model: torch.nn.Module
    density: torch.nn.Module
    box: Tuple[Sequence[float], Sequence[float]]
    iters: int
    resuming: bool = False
    needed: Set[str] = field(default_factory=set)
    background: Optional[Callable[[], torch.nn.ParameterDict]] = None
    products: Dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        device = self.rays.origins.device
        self.lo, self.hi = (torch.tensor(self.box[i], device=device) for i in (0, 1))


class Stage:
    """A method's work before and around training (see the module docstring); every hook does nothing
    by default."""

    def setup(self, state: MethodState, ctx) -> None:
        """Once, after the model is built."""

    def before_training(self, state: MethodState, ctx, budget: TimeBudget) -> bool:
        """Once, before the first step; False: interrupted (the run stops)."""
        return True

    def on_step(self, state: MethodState, nominal: float) -> Dict[str, float]:
        """At each step, before the forward pass (``nominal``: the step the schedules read,
        :class:`~l3d_app.runtime.horizon.Horizon`); figures to log."""
        return {}

    def metrics(self) -> Dict[str, Any]:
        """Figures for metrics.json."""
        return {}


class Stages:
    """A method's stages in config order; each hook calls every stage's."""

    def __init__(self, stages: Mapping[str, Stage]):
        self.stages: Dict[str, Stage] = dict(stages)

    @classmethod
    def build(cls, cfg: Mapping[str, Mapping]) -> "Stages":
        """``{key: STAGES.build(entry)}`` of a ``stages`` config (key -> ``{name: ..., ...}``)."""
        return cls({str(key): STAGES.build(entry) for key, entry in (cfg or {}).items()})

    def setup(self, state: MethodState, ctx) -> None:
        for stage in self.stages.values():
            stage.setup(state, ctx)

    def before_training(self, state: MethodState, ctx, budget: TimeBudget) -> Optional[str]:
        """The key of the stage that was interrupted, else None."""
        for key, stage in self.stages.items():
            if not stage.before_training(state, ctx, budget):
                return key
        return None

    def on_step(self, state: MethodState, nominal: float) -> Dict[str, float]:
        logs: Dict[str, float] = {}
        for stage in self.stages.values():
            logs.update(stage.on_step(state, nominal))
        return logs

    def metrics(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {}
        for stage in self.stages.values():
            out.update(stage.metrics())
        return out
