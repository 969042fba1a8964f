"""pointnet_cls: point-cloud classification (PointNet or DGCNN, ``model=...``).

    python main.py task=pointnet_cls                       # built-in chairs / vases / lamps
    python main.py task=pointnet_cls data=course_pointcloud data.root=DIR
    torchrun --nproc_per_node=2 main.py task=pointnet_cls  # data-parallel

Writes best.pt (best VALIDATION accuracy so far; test read once at the end), checkpoint.pt (resume), confusion_matrix.png,
vis/*.gif (random test clouds coloured by predicted class, one failure per class) and
metrics.json (accuracy, per-class accuracy, seconds, n_params, ...). See
:mod:`l3d_app.tasks.point_common`.
"""

from __future__ import annotations

from l3d_app.registry import TASKS
from l3d_app.tasks.point_common import run_point_task


@TASKS.register("pointnet_cls")
def pointnet_cls(cfg, ctx) -> dict:
    """Train and evaluate a point-cloud classifier."""
    return run_point_task(cfg, ctx, "cls")
