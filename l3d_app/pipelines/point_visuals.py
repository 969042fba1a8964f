"""Pictures of a point network's test predictions: a confusion matrix, turntable gifs of clouds, rotated rows."""

from __future__ import annotations

from typing import Any, Dict, List, Optional

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.metrics.accuracy import confusion_matrix
from l3d_app.pipelines.point_nets import Evaluation
from l3d_app.render.charts import confusion_image
from l3d_app.render.palette import palette
from l3d_app.render.points.cloud_row import cloud_row, correctness_colors
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.media import save_gif, save_png


def _safe(name: str) -> str:
    """A label usable in a file name ('chair/seat' -> 'chair-seat')."""
    return "".join(ch if ch.isalnum() or ch in "._-" else "-" for ch in str(name))


class Turntable:
    """Renders point clouds as turntable frames: ``renderer(cloud, cameras)``, ``cams`` the orbit,
    at most ``max_points`` points (a fixed random subset), the cloud normalised first."""

    def __init__(self, renderer, cams: Cameras, max_points: int, device):
        self.renderer, self.cams, self.max_points, self.device = renderer, cams, int(max_points), device

    def __call__(self, points: torch.Tensor, colors: torch.Tensor) -> torch.Tensor:
        """points (P, 3), colors (P, 3) -> frames (F, H, W, 3) on the CPU (cloud normalised)."""
        keep = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(0))[:self.max_points]
        cloud = PointCloud(points[keep].float(), colors=colors[keep].float()).normalized().to(self.device)
        return self.renderer(cloud, self.cams)["image"].cpu()


def rotation_row(renderer, camera: Cameras, ev: Evaluation, kind: str, labels: Optional[torch.Tensor],
                 n: int, n_parts: int) -> torch.Tensor:
    """(H, k W, 3) picture: the first test cloud of each class (``labels`` (N,); the first clouds when None), at
    most ``n``, as ``ev`` saw them (rotated), seen by ``camera``; cls: green where the class was right, red where
    wrong; seg: the predicted parts' colours (``n_parts`` of them)."""
    firsts = (list(range(min(n, ev.pred.shape[0]))) if labels is None else
              [int((labels == c).nonzero()[0]) for c in torch.unique(labels).tolist()][:n])
    index = torch.tensor(firsts)
    if kind == "cls":
        colors = correctness_colors(ev.pred[index] == ev.target[index], ev.points.shape[1])
    else:
        colors = palette(n_parts)[ev.pred[index]]
    return cloud_row(renderer, camera, list(ev.points[index]), list(colors))


def write_visuals(ctx, ev: Evaluation, kind: str, names: List[str], class_of: Optional[torch.Tensor],
                  class_names: List[str], table: Optional[Turntable], num_vis: int, vis_failures: bool, fps: float,
                  seed: int, budget: TimeBudget) -> Dict[str, Any]:
    """Confusion matrix PNG, gifs (``table``'s turntable, ``fps``) of ``num_vis`` random test clouds (drawn
    with ``seed``) coloured by prediction (seg: truth | prediction side by side) and, with ``vis_failures``,
    of one failure per class; under ``budget`` each gif only while the last one's cost still fits.
    Returns counts for metrics."""
    k = len(names)
    cm = confusion_matrix(ev.pred, ev.target, k)
    image = confusion_image(cm, names, f"pointnet_{kind}: test accuracy {ev.accuracy:.4f}")
    save_png(ctx.path("confusion_matrix.png"), image)
    ctx.logger.image("test/confusion_matrix", image)
    if int(num_vis) <= 0 and not vis_failures:
        return {}
    left = budget.seconds_left()
    if left is not None and left <= 0:         # gifs are previews: under a spent budget, none
        budget.note("test/gifs", f"time budget {budget.seconds:g} s: spent before the gifs (not written)")
        return {"gifs_skipped": True}
    colors = palette(k)

    def gif(name: str, i: int) -> None:
        if kind == "cls":
            frames = table(ev.points[i], colors[ev.pred[i]].expand(ev.points.shape[1], 3))
        else:
            frames = torch.cat([table(ev.points[i], colors[ev.target[i]]),
                                table(ev.points[i], colors[ev.pred[i]])], dim=2)
        save_gif(ctx.path(name), frames, fps=float(fps))

    gen = torch.Generator().manual_seed(int(seed))
    chosen = torch.randperm(ev.pred.shape[0], generator=gen)[:int(num_vis)].tolist()
    jobs = []                                   # (file name, cloud index, is a failure gif)
    for n, i in enumerate(chosen):
        truth = class_names[int(class_of[i])] if class_of is not None else "cloud"
        pred = names[int(ev.pred[i])] if kind == "cls" else f"acc{float((ev.pred[i] == ev.target[i]).float().mean()):.3f}"
        jobs.append((f"vis/sample{n}_{_safe(truth)}_pred-{_safe(pred)}.gif", i, False))
    if vis_failures:
        groups = class_of if class_of is not None else torch.zeros(ev.pred.shape[0], dtype=torch.long)
        for c in torch.unique(groups).tolist():
            members = torch.nonzero(groups == c).squeeze(1)
            if kind == "cls":
                wrong = members[ev.pred[members] != ev.target[members]]
                if wrong.numel() == 0:
                    continue
                i = int(wrong[0])
                label = f"{class_names[c]}_as_{names[int(ev.pred[i])]}"
            else:
                acc = (ev.pred[members] == ev.target[members]).float().mean(1)
                i = int(members[acc.argmin()])
                label = f"{class_names[c] if class_of is not None else 'worst'}_acc{float(acc.min()):.3f}"
            jobs.append((f"vis/failure_{_safe(label)}.gif", i, True))
    written, last = [], 0.0
    for name, i, failure in jobs:     # under a budget, each gif only while the last one's cost still fits
        left = budget.seconds_left()
        if left is not None and left < last:
            budget.note("test/gifs", f"time budget {budget.seconds:g} s: {len(written)} of {len(jobs)} gifs "
                                     f"fit ({left:.1f} s left at {last:.2f} s per gif)")
            break
        t0 = budget.clock()
        gif(name, i)
        last = budget.clock() - t0
        written.append(failure)
    return {"n_vis": written.count(False), "n_failure_gifs": written.count(True)}
