"""PointNet++ with single-scale grouping (Qi et al. 2017b), for classification and part segmentation.

Pipeline (shapes for B clouds of N points, world units; the built-in clouds lie in the unit ball):

* set abstraction ``l`` (one per entry of ``sa_points``): ``M_l`` centres chosen by
  :func:`farthest_point_sample` among the previous level's points; around each, the first
  ``sa_neighbors[l]`` points (in index order) within ``sa_radii[l]`` (:func:`ball_query`);
  their coordinates relative to the centre (divided by the radius), concatenated with their features, go through a
  shared MLP (``sa_widths[l]``) and are max-pooled: (B, M_l, C_l);
* a global layer: shared MLP (``global_widths``) on every remaining point (coordinates +
  features) and a max over points: (B, C);
* classification: an MLP head (``cls_head``, dropout) on the global feature -> (B, K);
* segmentation: feature propagation back to every input point: inverse-distance weighted
  interpolation from the 3 nearest points of the coarser level (:func:`three_nn_interpolate`),
  concatenated with the finer level's features, shared MLP (``fp_widths``), then a per-point
  head -> (B, N, K).

Sampling and grouping are pure torch and vectorised over clouds, centres and points; only
the M iterations of farthest-point sampling run in a Python loop (each picks one centre per
cloud from all N distances at once). The order of the input points matters slightly (the
first sampled centre is point 0, and a ball keeps its first k members by index), as in the
reference implementation.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Sequence

import torch
from torch import nn

from l3d_app.errors import UserError
from l3d_app.models.pointnet import mlp_head, shared_mlp
from l3d_app.registry import MODELS


def farthest_point_sample(xyz: torch.Tensor, m: int) -> torch.Tensor:
    """(B, m) long indices of ``m`` points of each cloud ``xyz`` (B, N, 3) by farthest-point
    sampling: start at point 0, then repeatedly take the point farthest (Euclidean) from those
    chosen so far (ties: the lowest index). ``m`` <= N."""
    B, N, _ = xyz.shape
    if not 0 < m <= N:
        raise UserError(f"farthest_point_sample needs 0 < m <= N={N}, got m={m}")
    idx = torch.zeros(B, m, dtype=torch.long, device=xyz.device)
    nearest = torch.full((B, N), float("inf"), dtype=xyz.dtype, device=xyz.device)
    rows = torch.arange(B, device=xyz.device)
    last = torch.zeros(B, dtype=torch.long, device=xyz.device)
    for i in range(1, m):  # one centre per iteration, all clouds and points at once
        d = (xyz - xyz[rows, last][:, None]).square().sum(-1)
        nearest = torch.minimum(nearest, d)
        last = nearest.argmax(dim=1)
        idx[:, i] = last
    return idx


def ball_query(xyz: torch.Tensor, centers: torch.Tensor, radius: float, k: int) -> torch.Tensor:
    """(B, M, k) long indices into ``xyz`` (B, N, 3) of the first ``k`` points (by index)
    within ``radius`` (inclusive) of each centre (B, M, 3); balls with fewer than ``k``
    members repeat their first member; an empty ball (a centre not among the points and
    nothing in reach) gets its nearest point."""
    B, N, _ = xyz.shape
    d2 = torch.cdist(centers, xyz).square()                                # (B, M, N)
    order = torch.arange(N, device=xyz.device).expand_as(d2)
    keyed = torch.where(d2 <= float(radius) ** 2, order, torch.full_like(order, N))
    first = keyed.topk(min(k, N), dim=-1, largest=False, sorted=True).values  # (B, M, k')
    nearest = d2.argmin(dim=-1, keepdim=True)
    head = torch.where(first[..., :1] < N, first[..., :1], nearest)
    first = torch.where(first < N, first, head)
    if first.shape[-1] < k:                                                 # fewer points than k
        first = torch.cat([first, head.expand(-1, -1, k - first.shape[-1])], dim=-1)
    return first


def gather(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """values (B, N, C) at idx (B, ...) -> (B, ..., C)."""
    B = values.shape[0]
    flat = idx.reshape(B, -1)
    out = torch.gather(values, 1, flat[..., None].expand(-1, -1, values.shape[-1]))
    return out.view(*idx.shape, values.shape[-1])


def three_nn_interpolate(fine_xyz: torch.Tensor, coarse_xyz: torch.Tensor, coarse_feat: torch.Tensor,
                         eps: float = 1e-8) -> torch.Tensor:
    """Features at ``fine_xyz`` (B, N, 3) interpolated from the 3 nearest coarse points
    (B, M, 3) with features (B, M, C), weights 1 / (distance + eps) normalised -> (B, N, C)."""
    k = min(3, coarse_xyz.shape[1])
    d, idx = torch.cdist(fine_xyz, coarse_xyz).topk(k, dim=-1, largest=False)   # (B, N, k)
    w = 1.0 / (d + eps)
    w = w / w.sum(-1, keepdim=True)
    return (gather(coarse_feat, idx) * w[..., None]).sum(dim=2)


class SetAbstraction(nn.Module):
    """One single-scale-grouping level: (xyz (B, N, 3), feat (B, N, C) or None) ->
    (centres (B, M, 3), features (B, M, widths[-1]))."""

    def __init__(self, num_centers: int, radius: float, k: int, in_dim: int, widths: Sequence[int],
                 bn_momentum: float = 0.1):
        super().__init__()
        self.m, self.radius, self.k = int(num_centers), float(radius), int(k)
        self.mlp = shared_mlp([in_dim + 3, *widths], bn_momentum=bn_momentum)
        self.out_dim = int(widths[-1])

    def forward(self, xyz: torch.Tensor, feat: Optional[torch.Tensor]):
        m = min(self.m, xyz.shape[1])
        centers = gather(xyz, farthest_point_sample(xyz.detach(), m))              # (B, M, 3)
        nbr = ball_query(xyz.detach(), centers.detach(), self.radius, self.k)      # (B, M, k)
        grouped = (gather(xyz, nbr) - centers[:, :, None]) / self.radius            # (B, M, k, 3), unit ball
        if feat is not None:
            grouped = torch.cat([grouped, gather(feat, nbr)], dim=-1)
        return centers, self.mlp(grouped).max(dim=2).values


class PointNet2(nn.Module):
    """PointNet++ SSG (see the module docstring); forward: (B, N, 3) -> {"logits": ...}."""

    def __init__(self, task: str, num_outputs: int, sa_points: Sequence[int], sa_radii: Sequence[float],
                 sa_neighbors: Sequence[int], sa_widths: Sequence[Sequence[int]], global_widths: Sequence[int],
                 cls_head: Sequence[int], seg_head: Sequence[int], fp_widths: Sequence[int], dropout: float,
                 bn_momentum: float = 0.5):
        super().__init__()
        bn = float(bn_momentum)
        n = len(sa_points)
        if not (n == len(sa_radii) == len(sa_neighbors) == len(sa_widths)) or n == 0:
            raise UserError("pointnet2: sa_points, sa_radii, sa_neighbors and sa_widths need the same, "
                            f"non-zero length, got {len(sa_points)}, {len(sa_radii)}, {len(sa_neighbors)}, "
                            f"{len(sa_widths)}")
        if task not in ("cls", "seg"):
            raise UserError(f"pointnet2 task must be 'cls' or 'seg', got {task!r}")
        self.task = task
        self.sa = nn.ModuleList()
        dim = 0
        dims: List[int] = [0]
        for m, r, k, w in zip(sa_points, sa_radii, sa_neighbors, sa_widths):
            self.sa.append(SetAbstraction(m, r, k, dim, [int(x) for x in w], bn))
            dim = self.sa[-1].out_dim
            dims.append(dim)
        self.global_mlp = shared_mlp([dim + 3, *[int(x) for x in global_widths]], bn_momentum=bn)
        g = int(global_widths[-1])
        if task == "cls":
            self.head = mlp_head([g, *[int(x) for x in cls_head], int(num_outputs)], float(dropout), bn)
            return
        # feature propagation: global -> level n, then level l+1 -> level l, down to the input points
        fp = int(fp_widths[0]) if fp_widths else 128
        self.fp = nn.ModuleList()
        coarse = g
        for fine in reversed(dims):
            self.fp.append(shared_mlp([coarse + fine + (3 if fine == 0 else 0), fp], bn_momentum=bn))
            coarse = fp
        self.head = nn.Sequential(shared_mlp([fp, *[int(x) for x in seg_head]], bn_momentum=bn),
                                  nn.Linear(int(seg_head[-1]) if seg_head else fp, int(num_outputs)))

    def forward(self, points: torch.Tensor) -> Dict[str, torch.Tensor]:
        if points.dim() != 3 or points.shape[-1] != 3:
            raise UserError(f"pointnet2 expects (B, N, 3) points, got {tuple(points.shape)}")
        xyz, feat = points, None
        levels = [(xyz, feat)]
        for layer in self.sa:
            xyz, feat = layer(xyz, feat)
            levels.append((xyz, feat))
        glob = self.global_mlp(torch.cat([xyz, feat], dim=-1)).max(dim=1).values     # (B, G)
        if self.task == "cls":
            return {"logits": self.head(glob)}
        up = glob[:, None]                                                              # one point: the global feature
        up_xyz = xyz.mean(dim=1, keepdim=True)
        for fp, (lx, lf) in zip(self.fp, reversed(levels)):
            inter = up.expand(-1, lx.shape[1], -1) if up.shape[1] == 1 else three_nn_interpolate(lx, up_xyz, up)
            skip = lf if lf is not None else lx                                         # input level: coordinates
            up, up_xyz = fp(torch.cat([inter, skip], dim=-1)), lx
        return {"logits": self.head(up)}


@MODELS.register("pointnet2")
def pointnet2(task: str, num_outputs: int, sa_points: Sequence[int] = (128, 32),
              sa_radii: Sequence[float] = (0.25, 0.5), sa_neighbors: Sequence[int] = (32, 32),
              sa_widths: Sequence[Sequence[int]] = ((32, 32, 64), (64, 64, 128)),
              global_widths: Sequence[int] = (128, 256, 512), cls_head: Sequence[int] = (256, 128),
              seg_head: Sequence[int] = (128,), fp_widths: Sequence[int] = (128,), dropout: float = 0.3,
              bn_momentum: float = 0.5, device: Optional[torch.device] = None) -> nn.Module:
    """Build a PointNet++ SSG for ``task`` ('cls' or 'seg') with ``num_outputs`` classes/parts.
    ``bn_momentum``: BatchNorm running-statistics momentum (the reference starts at 0.5; with
    PyTorch's 0.1 the running statistics lag the fast-moving first layers in short runs, and
    the eval-mode model can collapse to one class)."""
    model = PointNet2(task, int(num_outputs), list(sa_points), list(sa_radii), list(sa_neighbors),
                      [list(w) for w in sa_widths], list(global_widths), list(cls_head), list(seg_head),
                      list(fp_widths), float(dropout), float(bn_momentum))
    return model.to(device) if device is not None else model
