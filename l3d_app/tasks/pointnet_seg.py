"""pointnet_seg: per-point part segmentation (PointNet or DGCNN, ``model=...``).

    python main.py task=pointnet_seg                       # built-in parts (10 global labels)
    python main.py task=pointnet_seg data=course_pointcloud data.root=DIR

Writes best.pt, checkpoint.pt, confusion_matrix.png (parts), vis/*.gif (truth | prediction
side by side, random test clouds and the worst cloud of each class) and metrics.json
(``accuracy`` = point accuracy, ``miou``, per-part IoU, seconds, n_params, ...). See
:mod:`l3d_app.tasks.point_common`.
"""

from __future__ import annotations

from l3d_app.registry import TASKS
from l3d_app.tasks.point_common import run_point_task


@TASKS.register("pointnet_seg")
def pointnet_seg(cfg, ctx) -> dict:
    """Train and evaluate a per-point part segmenter."""
    return run_point_task(cfg, ctx, "seg")
