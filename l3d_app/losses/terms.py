"""Loss terms: a method's loss as a sum of named, weighted, scheduled terms (registry ``LOSS_TERMS``).

Each term is an object with its own ``weight`` and schedule (``start``, ``until``) that returns its
unweighted value for one training step (nerfstudio's loss dict); :class:`LossTerms` sums them, in config
order, as ``sum_k weight_k(step) * term_k(batch)`` and logs each value as ``<key>_loss``. A task composes
them from config (``losses.<key>: {name: <registered name>, weight: ..., ...}``; a term whose weight is
0 is off), so a new term is a file, a register line and a yaml (docs/architecture.md).

Schedule, in the run's steps (``start``, ``until``: a number <= 1 is a fraction of ``iters``, a larger
one a step count): weight 0 before ``start``; from ``start`` the full weight, or with ``until`` set one
falling linearly to 0 at ``until``.

A term may read, once before training (:meth:`LossTerm.setup`), the method's shared state (its
model, density, training rays and what its stages produced, ``state.products``): a term that
``needs`` a product no stage made is off for the run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Set, Tuple, Union

import torch

from l3d_app.errors import UserError
from l3d_app.registry import LOSS_TERMS

Value = Union[torch.Tensor, Tuple[torch.Tensor, Dict[str, float]]]


@dataclass
class Batch:
    """One training step as the loss terms see it.

    Attributes:
        state: the method's shared state (:class:`~l3d_app.stages.base.MethodState`: ``model``,
            ``density``, ``rays`` (the training rays), ``products``, ``lo``/``hi`` (the scene box)).
        rays: (B,) long, the batch's indices into ``state.rays``.
        origins, dirs: (B, 3) the batch's rays (unit ``dirs``, world units).
        target: (B, 3) their pixels' colours in [0, 1].
        out: the render of the batch (``color``, ``optical_depth``, ``weights``, ``t``, ``sdf``, ``grad``,
            ``ray_indices``, ... per :func:`~l3d_app.render.sdf.volume.render_sdf_rays`).
        progress: the schedules' position, the (nominal) step over ``iters``.
        generator: the run's random generator (a term that draws points uses it).
    """

    state: Any
    rays: torch.Tensor
    origins: torch.Tensor
    dirs: torch.Tensor
    target: torch.Tensor
    out: Dict[str, torch.Tensor]
    progress: float
    generator: Optional[torch.Generator] = None


def _schedule_point(value, key: str) -> Optional[float]:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
        raise UserError(f"{key} must be null or a number >= 0 (<= 1: a fraction of the steps, else steps), "
                        f"got {value!r}")
    return float(value)


class LossTerm:
    """One term of a method's loss: ``weight`` x ``term(batch)`` while its schedule is on.

    Args:
        weight: its weight (>= 0; 0: off).
        start: the step (> 1) or fraction of the steps (<= 1) from which it counts.
        until: null, or where its weight has fallen linearly to 0 (after ``start``).

    Subclasses implement ``__call__(batch) -> value`` or ``(value, {figure: float})`` (``value`` a scalar
    tensor) and may override :meth:`setup`; ``needs`` names a stage product they read.
    """

    needs: Optional[str] = None

    def __init__(self, weight: float = 1.0, start: float = 0.0, until: Optional[float] = None):
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or weight < 0:
            raise UserError(f"a loss term's weight must be a number >= 0, got {weight!r}")
        self.weight = float(weight)
        self.start = _schedule_point(start, "start") or 0.0
        self.until = _schedule_point(until, "until")
        if self.until is not None and not self.until > self.start:
            raise UserError(f"until must lie after start, got start={start}, until={until}")

    def weight_at(self, progress: float, iters: int) -> float:
        """The weight at ``progress`` (step / ``iters``) under the schedule."""
        start, until = (None if x is None else (x if x <= 1.0 else x / max(int(iters), 1))
                        for x in (self.start, self.until))
        if progress < start:
            return 0.0
        if until is None:
            return self.weight
        return self.weight * max(0.0, 1.0 - (float(progress) - start) / (until - start))

    def setup(self, state) -> bool:
        """Once before training: read what the term needs from ``state``; False: off for this run."""
        return self.needs is None or state.products.get(self.needs) is not None

    def __call__(self, batch: Batch) -> Value:
        raise NotImplementedError


class LossTerms:
    """The named terms of a method's loss, summed in order (see the module docstring)."""

    def __init__(self, terms: Mapping[str, LossTerm]):
        self.terms: Dict[str, LossTerm] = dict(terms)
        self.active: Dict[str, LossTerm] = {}

    @classmethod
    def build(cls, cfg: Mapping[str, Mapping]) -> "LossTerms":
        """``{key: LOSS_TERMS.build(entry)}`` of a ``losses`` config (key -> ``{name: ..., ...}``)."""
        return cls({str(key): LOSS_TERMS.build(entry) for key, entry in (cfg or {}).items()})

    def needs(self) -> Set[str]:
        """The stage products that the terms with a weight read."""
        return {t.needs for t in self.terms.values() if t.needs is not None and t.weight > 0}

    def setup(self, state) -> None:
        """:meth:`LossTerm.setup` of each weighted term; those that say False stay off."""
        self.active = {key: t for key, t in self.terms.items() if t.weight > 0 and t.setup(state)}

    def __call__(self, batch: Batch, iters: int) -> Tuple[torch.Tensor, Dict[str, torch.Tensor]]:
        """(the weighted sum (), each term's value and figures for the log)."""
        total, logs = None, {}
        for key, term in self.active.items():
            w = term.weight_at(batch.progress, iters)
            if w <= 0:
                continue
            value = term(batch)
            value, figures = value if isinstance(value, tuple) else (value, {})
            total = w * value if total is None else total + w * value
            logs[f"{key}_loss"] = value.detach()
            logs.update({k: torch.tensor(v) for k, v in figures.items()})
        if total is None:
            raise UserError("no loss term has a weight at this step (losses.*.weight)")
        return total, logs
