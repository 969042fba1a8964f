"""PointNet (Qi et al. 2017) for point-cloud classification and part segmentation.

Every point goes through the same MLP (:class:`SharedMLP`: linear layers on the channels-
last features, BatchNorm over batch and points, ReLU); a max over points gives the global feature, so
the classifier's output does not depend on the order of the points and the segmenter's
per-point output permutes with them. Optional T-Nets predict a 3x3 input transform and a
64x64 feature transform (with the orthogonality regulariser ``|I - A A^T|_F^2``).

Shapes: input points (B, N, 3) in world units; classification logits (B, K);
segmentation logits (B, N, K).
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence

import torch
from torch import nn

from l3d_app.errors import UserError
from l3d_app.registry import MODELS


class SharedMLP(nn.Module):
    """The same MLP on every point: (..., C_in) -> (..., C_out), channels last.

    Linear + BatchNorm1d (statistics over all points of the batch) + ReLU per width step;
    the last ReLU is dropped when ``last_relu`` is False.
    """

    def __init__(self, widths: Sequence[int], last_relu: bool = True, bn_momentum: float = 0.1):
        super().__init__()
        layers = []
        for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
            layers += [nn.Linear(a, b, bias=False), nn.BatchNorm1d(b, momentum=bn_momentum)]
            if last_relu or i < len(widths) - 2:
                layers.append(nn.ReLU(inplace=True))
        self.layers = nn.Sequential(*layers)
        self.out_dim = widths[-1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x.reshape(-1, x.shape[-1])).view(*x.shape[:-1], self.out_dim)


def shared_mlp(widths: Sequence[int], last_relu: bool = True, bn_momentum: float = 0.1) -> SharedMLP:
    """A :class:`SharedMLP` with the given widths (input width first); ``bn_momentum``: the
    BatchNorm running-statistics momentum (PyTorch's default 0.1)."""
    return SharedMLP([int(w) for w in widths], last_relu, float(bn_momentum))


def mlp_head(widths: Sequence[int], dropout: float, bn_momentum: float = 0.1) -> nn.Sequential:
    """Fully connected head on (B, C): Linear+BN+ReLU(+Dropout) ..., last layer plain Linear."""
    layers = []
    for a, b in zip(widths[:-2], widths[1:-1]):
        layers += [nn.Linear(a, b, bias=False), nn.BatchNorm1d(b, momentum=float(bn_momentum)), nn.ReLU(inplace=True)]
        if dropout > 0:
            layers.append(nn.Dropout(dropout))
    layers.append(nn.Linear(widths[-2], widths[-1]))
    return nn.Sequential(*layers)


class GlobalLocalLinear(nn.Module):
    """Shared linear layer on ``concat(local_i, global)`` per point, + BatchNorm + ReLU.

    Computed as ``W_l local_i + W_g global`` (the same function as concatenating the
    global feature to every point, with the global half done once per cloud instead of
    once per point). local (B, N, C_l), global (B, C_g) -> (B, N, C_out).
    """

    def __init__(self, c_local: int, c_global: int, c_out: int):
        super().__init__()
        self.local = nn.Linear(c_local, c_out, bias=False)
        self.glob = nn.Linear(c_global, c_out, bias=False)
        self.post = nn.Sequential(nn.BatchNorm1d(c_out), nn.ReLU(inplace=True))

    def forward(self, local: torch.Tensor, glob: torch.Tensor) -> torch.Tensor:
        x = self.local(local) + self.glob(glob)[:, None, :]
        return self.post(x.reshape(-1, x.shape[-1])).view(x.shape)


class TNet(nn.Module):
    """Predicts a (B, k, k) transform from (B, N, k) features; initialised to the identity.
    Points transform as row vectors, ``x_i -> x_i A``."""

    def __init__(self, k: int, width: int = 256):
        super().__init__()
        self.k = k
        self.features = shared_mlp([k, 64, 128, width])
        self.head = mlp_head([width, width // 2, width // 4, k * k], dropout=0.0)
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        g = self.features(x).max(dim=1).values
        eye = torch.eye(self.k, device=x.device, dtype=x.dtype)
        return self.head(g).view(-1, self.k, self.k) + eye


def orthogonality_loss(transform: torch.Tensor) -> torch.Tensor:
    """Mean over the batch of ``|I - A A^T|_F^2`` for (B, k, k) transforms ``A``."""
    eye = torch.eye(transform.shape[-1], device=transform.device, dtype=transform.dtype)
    return (eye - transform @ transform.transpose(1, 2)).square().sum((1, 2)).mean()


class PointNetEncoder(nn.Module):
    """Per-point features and the max-pooled global feature.

    Args:
        widths: per-point MLP widths after the 3 input channels, e.g. (64, 128, 1024);
            the local feature used for segmentation is the output of the first layer.
        input_transform / feature_transform: use the 3x3 / first-width T-Nets.
    """

    def __init__(self, widths: Sequence[int] = (64, 128, 1024), input_transform: bool = False,
                 feature_transform: bool = False):
        super().__init__()
        widths = [int(w) for w in widths]
        if len(widths) < 2 or min(widths) < 1:
            raise UserError(f"pointnet widths need >= 2 positive entries, got {widths}")
        self.local_dim, self.global_dim = widths[0], widths[-1]
        self.stn = TNet(3) if input_transform else None
        self.fstn = TNet(widths[0]) if feature_transform else None
        self.first = shared_mlp([3, widths[0]])
        self.rest = shared_mlp(widths, last_relu=False)

    def forward(self, points: torch.Tensor) -> Dict[str, torch.Tensor]:
        """points (B, N, 3) -> local (B, N, C_local), global (B, C_global), and the
        feature transform (B, C_local, C_local) when enabled."""
        if points.dim() != 3 or points.shape[-1] != 3:
            raise UserError(f"pointnet expects (B, N, 3) points, got {tuple(points.shape)}")
        x = points
        if self.stn is not None:
            x = torch.bmm(x, self.stn(x))
        local = self.first(x)
        out = {}
        if self.fstn is not None:
            a = self.fstn(local)
            local = torch.bmm(local, a)
            out["feature_transform"] = a
        out["local"] = local
        out["global"] = self.rest(local).max(dim=1).values
        return out


class PointNetCls(nn.Module):
    """PointNet classifier: (B, N, 3) points -> (B, num_classes) logits."""

    def __init__(self, num_outputs: int, widths: Sequence[int] = (64, 128, 1024),
                 head: Sequence[int] = (512, 256), dropout: float = 0.3,
                 input_transform: bool = False, feature_transform: bool = False):
        super().__init__()
        self.encoder = PointNetEncoder(widths, input_transform, feature_transform)
        self.head = mlp_head([self.encoder.global_dim, *head, num_outputs], dropout)

    def forward(self, points: torch.Tensor) -> Dict[str, torch.Tensor]:
        enc = self.encoder(points)
        out = {"logits": self.head(enc["global"])}
        if "feature_transform" in enc:
            out["regulariser"] = orthogonality_loss(enc["feature_transform"])
        return out


class PointNetSeg(nn.Module):
    """PointNet segmenter: per-point features concatenated with the global feature, then a
    shared MLP: (B, N, 3) points -> (B, N, num_parts) logits."""

    def __init__(self, num_outputs: int, widths: Sequence[int] = (64, 128, 1024),
                 head: Sequence[int] = (256, 128), dropout: float = 0.0,
                 input_transform: bool = False, feature_transform: bool = False):
        super().__init__()
        self.encoder = PointNetEncoder(widths, input_transform, feature_transform)
        head = [int(h) for h in head]
        if not head:
            raise UserError("pointnet seg_head needs at least one width")
        self.fuse = GlobalLocalLinear(self.encoder.local_dim, self.encoder.global_dim, head[0])
        self.head = shared_mlp(head)
        self.dropout = nn.Dropout(dropout) if dropout > 0 else nn.Identity()
        self.out = nn.Linear(head[-1], num_outputs)

    def forward(self, points: torch.Tensor) -> Dict[str, torch.Tensor]:
        enc = self.encoder(points)
        x = self.fuse(enc["local"], enc["global"])
        out = {"logits": self.out(self.dropout(self.head(x)))}
        if "feature_transform" in enc:
            out["regulariser"] = orthogonality_loss(enc["feature_transform"])
        return out


@MODELS.register("pointnet")
def pointnet(task: str, num_outputs: int, widths: Sequence[int] = (64, 128, 1024),
             cls_head: Sequence[int] = (512, 256), seg_head: Sequence[int] = (256, 128),
             dropout: float = 0.3, input_transform: bool = False,
             feature_transform: bool = False, device: Optional[torch.device] = None) -> nn.Module:
    """Build a PointNet for ``task`` ('cls' or 'seg') with ``num_outputs`` classes/parts.

    ``widths`` are the shared per-point MLP widths; ``cls_head`` the classifier's hidden
    widths (dropout ``dropout``), ``seg_head`` the per-point segmentation head's widths.
    """
    kw = dict(widths=widths, input_transform=bool(input_transform),
              feature_transform=bool(feature_transform))
    if task == "cls":
        model = PointNetCls(int(num_outputs), head=cls_head, dropout=float(dropout), **kw)
    elif task == "seg":
        model = PointNetSeg(int(num_outputs), head=seg_head, **kw)
    else:
        raise UserError(f"pointnet task must be 'cls' or 'seg', got {task!r}")
    return model.to(device) if device is not None else model
