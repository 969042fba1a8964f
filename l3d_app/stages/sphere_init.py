"""The SDF model fitted to its initial sphere before training."""

from __future__ import annotations

from l3d_app.errors import UserError
from l3d_app.models.sdf_grid import pretrain_field
from l3d_app.registry import STAGES
from l3d_app.stages.base import MethodState, Stage


@STAGES.register("sphere_init")
class SphereInit(Stage):
    """``steps`` steps fitting the SDF model to ``|x| - radius`` (its own initial sphere, enclosing the
    scene, which training then carves: :func:`~l3d_app.models.sdf_grid.pretrain_field`) right after it is
    built; not when the run resumes from its checkpoint. 0: the geometric initialisation alone."""

    def __init__(self, steps: int = 200):
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise UserError(f"sphere_init steps must be an integer >= 0, got {steps!r}")
        self.steps = steps

    def setup(self, state: MethodState, ctx) -> None:
        if self.steps > 0 and not state.resuming:
            err = pretrain_field(state.model, state.box, self.steps, generator=ctx.generator)
            ctx.logger.text("pretrain", f"sphere pretraining: mean |f - sdf_sphere| = {err:.4g}")
