"""Densification strategies for Gaussian splatting: how the set of splats grows, shrinks and moves.

A strategy is a small class registered in :data:`l3d_app.registry.STRATEGIES` and chosen
with ``strategy=<name>`` (``conf/strategy/<name>.yaml``). It owns its schedule and its
state (checkpointed through ``state_dict`` / ``load_state_dict``) and is driven by the
training task through the hooks of :class:`~l3d_app.strategies.base.Strategy`
(``initialize``, ``regularization``, ``step_pre_backward``, ``step_post_backward``).
A new strategy is one file here, its register line, an import below and a yaml; no task
changes.

* ``default`` (:mod:`.default`): 3DGS adaptive density control (clone / split / prune,
  opacity reset, cap).
* ``mcmc`` (:mod:`.mcmc`): 3DGS-MCMC: a fixed budget, dead splats relocated onto live ones,
  opacity-gated noise on the means, opacity and scale regularisers.
* ``course`` (:mod:`.course`): the course's baseline: a fixed set (no densification).
"""

from l3d_app.strategies.base import Strategy
from l3d_app.strategies import course, default, mcmc  # noqa: F401  (registration)

__all__ = ["Strategy"]
