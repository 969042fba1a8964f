"""DGCNN (Wang et al. 2019): edge convolutions over k-nearest-neighbour graphs.

The locality-aware alternative to PointNet (``model=dgcnn``). Each EdgeConv layer builds
the kNN graph of its input features (the first layer in xyz, later layers in feature
space: a *dynamic* graph), applies a shared MLP to every edge feature
``[x_i, x_j - x_i]`` and max-pools over the k neighbours. The per-layer features are
concatenated, embedded, and max-pooled over points for the global feature.
Classification: (B, N, 3) -> (B, K) logits; segmentation: (B, N, 3) -> (B, N, K).

The kNN here is batched over clouds and works in any feature dimension (the geometry
module's :func:`l3d_app.geometry.normals.knn` is single-cloud, 3-D); with N = 1024 points
the (B, N, N) distance matrix is small. Cost grows as N^2, so evaluate large clouds in
small batches.
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence

import torch
from torch import nn

from l3d_app.errors import UserError
from l3d_app.models.pointnet import GlobalLocalLinear, mlp_head, shared_mlp
from l3d_app.registry import MODELS


def batched_knn(x: torch.Tensor, k: int, chunk: int = 2048) -> torch.Tensor:
    """(B, N, k) long indices of the k nearest points of each point in features x (B, N, C)
    (Euclidean, ranked by ``|x_j|^2 - 2 x_i . x_j``; each point is normally its own first
    neighbour). Queries go ``chunk`` at a time, so memory is B * chunk * N distances.
    Not differentiable."""
    with torch.no_grad():
        sq = x.square().sum(-1)
        out = []
        for s in range(0, x.shape[1], chunk):
            d = sq[:, None, :] - 2 * x[:, s:s + chunk] @ x.transpose(1, 2)
            out.append(d.topk(k, dim=-1, largest=False).indices)
        return torch.cat(out, dim=1)


def edge_features(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Edge features (B, N, k, 2C) = [x_i, x_j - x_i] for x (B, N, C) and kNN idx (B, N, k)."""
    B, N, C = x.shape
    k = idx.shape[-1]
    neighbours = torch.gather(x, 1, idx.reshape(B, N * k, 1).expand(-1, -1, C)).view(B, N, k, C)
    centre = x[:, :, None, :].expand(-1, -1, k, -1)
    return torch.cat([centre, neighbours - centre], dim=-1)


class EdgeConv(nn.Module):
    """One EdgeConv: shared MLP on edge features, max over neighbours: (B, N, C) -> (B, N, C')."""

    def __init__(self, c_in: int, c_out: int, k: int):
        super().__init__()
        self.k = k
        self.mlp = nn.Sequential(nn.Linear(2 * c_in, c_out, bias=False), nn.BatchNorm1d(c_out),
                                 nn.LeakyReLU(0.2, inplace=True))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        idx = batched_knn(x, min(self.k, x.shape[1]))
        e = edge_features(x, idx)
        return self.mlp(e.reshape(-1, e.shape[-1])).view(*e.shape[:-1], -1).max(dim=2).values


class DGCNN(nn.Module):
    """DGCNN backbone + classification or segmentation head.

    Args:
        task: 'cls' or 'seg'.
        num_outputs: number of classes (cls) or parts (seg).
        widths: EdgeConv output widths, e.g. (64, 64, 128).
        k: neighbours per point.
        emb: width of the embedding before the global max-pool.
        cls_head / seg_head: hidden widths of the heads; dropout in the cls head.
    """

    def __init__(self, task: str, num_outputs: int, widths: Sequence[int] = (64, 64, 128),
                 k: int = 16, emb: int = 512, cls_head: Sequence[int] = (256, 128),
                 seg_head: Sequence[int] = (256, 128), dropout: float = 0.3):
        super().__init__()
        if task not in ("cls", "seg"):
            raise UserError(f"dgcnn task must be 'cls' or 'seg', got {task!r}")
        if int(k) < 1:
            raise UserError(f"dgcnn k must be >= 1, got {k}")
        self.task = task
        if len(widths) < 1 or min(int(w) for w in widths) < 1:
            raise UserError(f"dgcnn widths need >= 1 positive entry (one per EdgeConv), got {list(widths)}")
        dims = [3] + [int(w) for w in widths]
        self.convs = nn.ModuleList(EdgeConv(a, b, int(k)) for a, b in zip(dims[:-1], dims[1:]))
        local = sum(dims[1:])
        self.embed = shared_mlp([local, int(emb)])
        if task == "cls":
            self.head = mlp_head([int(emb), *cls_head, int(num_outputs)], float(dropout))
        else:
            seg_head = [int(h) for h in seg_head]
            if not seg_head:
                raise UserError("dgcnn seg_head needs at least one width")
            self.fuse = GlobalLocalLinear(local, int(emb), seg_head[0])
            self.head = nn.Sequential(shared_mlp(seg_head), nn.Linear(seg_head[-1], int(num_outputs)))

    def forward(self, points: torch.Tensor) -> Dict[str, torch.Tensor]:
        if points.dim() != 3 or points.shape[-1] != 3:
            raise UserError(f"dgcnn expects (B, N, 3) points, got {tuple(points.shape)}")
        feats, x = [], points
        for conv in self.convs:
            x = conv(x)
            feats.append(x)
        local = torch.cat(feats, dim=-1)  # (B, N, C)
        glob = self.embed(local).max(dim=1).values
        if self.task == "cls":
            return {"logits": self.head(glob)}
        return {"logits": self.head(self.fuse(local, glob))}


@MODELS.register("dgcnn")
def dgcnn(task: str, num_outputs: int, widths: Sequence[int] = (64, 64, 128), k: int = 16,
          emb: int = 512, cls_head: Sequence[int] = (256, 128), seg_head: Sequence[int] = (256, 128),
          dropout: float = 0.3, device: Optional[torch.device] = None) -> nn.Module:
    """Build a :class:`DGCNN` for ``task`` ('cls' or 'seg')."""
    model = DGCNN(task, num_outputs, widths, k, emb, cls_head, seg_head, dropout)
    return model.to(device) if device is not None else model
