"""``strategy=course``: the course's Gaussian-splatting baseline (CMU 16-825, assignment 4).

The course trains a FIXED set of isotropic Gaussians (one scale each) from the given
points with an L1 loss, no spherical harmonics beyond the DC colour and no densification.
As a strategy that is "change nothing": this class keeps the count fixed (and checks, on
``initialize``, that it was handed a set it can keep). The other parts of the baseline are
top-level knobs the strategy's yaml sets (``conf/strategy/course.yaml``: ``isotropic``,
``ssim_lambda: 0``, ``sh_degree: 0``, learning rates), so each can be switched back one
at a time for an ablation.
"""

from __future__ import annotations

from l3d_app.errors import UserError
from l3d_app.registry import STRATEGIES
from l3d_app.strategies.base import Strategy


@STRATEGIES.register("course")
class CourseStrategy(Strategy):
    """Fixed count: no clone, split, prune, relocation or opacity reset."""

    def initialize(self, model, optimizer, scene_extent: float) -> None:
        super().initialize(model, optimizer, scene_extent)
        if model.num == 0:
            raise UserError("strategy=course keeps the initial Gaussians and got none")
