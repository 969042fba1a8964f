"""A row of labelled point clouds seen by one camera: the robustness pictures (one row per rotation angle)."""

from __future__ import annotations

from typing import Sequence

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.pointcloud import PointCloud

CORRECT = (0.20, 0.65, 0.30)      # a cloud whose class was predicted right
WRONG = (0.85, 0.20, 0.20)        # ... and wrong


def correctness_colors(correct: torch.Tensor, num_points: int) -> torch.Tensor:
    """(B, P, 3) colours: every point of cloud b green where ``correct[b]`` (B,) bool, red otherwise."""
    c = torch.where(correct.bool().cpu()[:, None], torch.tensor(CORRECT), torch.tensor(WRONG))
    return c[:, None, :].expand(-1, int(num_points), 3)


@torch.no_grad()
def cloud_row(renderer, camera: Cameras, points: Sequence[torch.Tensor], colors: Sequence[torch.Tensor]
              ) -> torch.Tensor:
    """(H, n W, 3) CPU image: cloud k (points (P_k, 3) world units, colours (P_k, 3) in [0, 1]) rendered by
    ``renderer(PointCloud, camera)`` as is (no re-centring: a rotation stays visible), left to right."""
    device = camera.R.device
    frames = [renderer(PointCloud(p.float().to(device), colors=c.float().to(device)), camera)["image"][0].cpu()
              for p, c in zip(points, colors)]
    return torch.cat(frames, dim=1)
