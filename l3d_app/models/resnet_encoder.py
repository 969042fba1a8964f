"""The course's single-view encoder: ResNet-18 (He et al. 2016) without its classifier, in plain PyTorch.

``(B, H, W, 3)`` images in [0, 1] -> ``(B, 512)`` features: ImageNet normalisation (mean
(0.485, 0.456, 0.406), std (0.229, 0.224, 0.225)), the 7x7 stride-2 stem, a 3x3 stride-2 max pool,
four stages of two basic blocks (64, 128, 256, 512 channels; the last three halve the resolution)
and a global average pool, as the course's ``nn.Sequential(*list(resnet18.children())[:-1])``. Any
square side >= 32 works (32 px ends at 1x1 before the pool).

Parameter and buffer names follow torchvision's ``resnet18`` (``conv1``, ``bn1``, ``layer1.0.conv1``,
``layer2.0.downsample.0``, ...), so a state dict the user has on disk (torchvision's ImageNet file
or one of their own) loads with :func:`load_resnet18_weights`; its ``fc.*`` entries are ignored.
Nothing is downloaded: without a file the weights are randomly initialised (Kaiming, as torchvision).
"""

from __future__ import annotations

import os
from typing import Dict

import torch
from torch import nn

from l3d_app.errors import UserError
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.torch_files import read_torch_file

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with batch norm and an identity (or 1x1 strided) shortcut."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + (x if self.downsample is None else self.downsample(x)))


class ResNet18Encoder(nn.Module):
    """ResNet-18 trunk + global average pool: images (B, H, W, 3) in [0, 1] -> (B, 512)."""

    def __init__(self, image_size: int = 32):
        super().__init__()
        if int(image_size) < 32:
            raise UserError(f"encoder=resnet18 needs images of at least 32 px (it downsamples 32x), got {image_size}")
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        widths, cin, stages = (64, 128, 256, 512), 64, []
        for i, w in enumerate(widths):
            stages.append(nn.Sequential(BasicBlock(cin, w, 1 if i == 0 else 2), BasicBlock(w, w)))
            cin = w
        self.layer1, self.layer2, self.layer3, self.layer4 = stages
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.latent_dim = 512
        for m in self.modules():                          # torchvision's initialisation
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, H, W, 3) in [0, 1] -> (B, 512)."""
        if images.dim() != 4 or images.shape[-1] != 3:
            raise UserError(f"image encoder expects (B, H, W, 3) images, got {tuple(images.shape)}")
        x = (images.permute(0, 3, 1, 2) - self.mean) / self.std
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return self.avgpool(x).flatten(1)


def load_resnet18_weights(encoder: ResNet18Encoder, path: os.PathLike) -> int:
    """Load a ResNet-18 state dict from ``path`` (a torchvision-layout file; a checkpoint holding it under
    ``state_dict`` or ``model``, or with a ``module.`` prefix, works too; ``fc.*`` is ignored) into
    ``encoder``. Returns the number of tensors loaded. A missing file, an unreadable one, or one whose
    names or shapes are not ResNet-18's is a one-line :class:`UserError`."""
    file = resolve_path(path)
    if not file.is_file():
        raise UserError(f"encoder weights not found: {file} (encoder.weights=FILE: a local ResNet-18 state dict; "
                        "nothing is downloaded)")
    state = read_torch_file(file, "ResNet-18 state dict", weights_only=True)
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict) or not all(torch.is_tensor(v) for v in state.values()):
        raise UserError(f"{file} does not hold a state dict of tensors (a ResNet-18's, torchvision layout)")
    state = {(k[7:] if k.startswith("module.") else k): v for k, v in state.items()}
    state = {k: v for k, v in state.items() if not k.startswith("fc.")}
    own: Dict[str, torch.Tensor] = encoder.state_dict()
    missing = sorted(set(own) - set(state))
    extra = sorted(set(state) - set(own))
    shapes = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or extra or shapes:
        what = (f"missing {len(missing)} (e.g. {missing[0]})" if missing else
                f"unexpected {len(extra)} (e.g. {extra[0]})" if extra else
                f"{shapes[0]} is {tuple(state[shapes[0]].shape)}, ResNet-18 has {tuple(own[shapes[0]].shape)}")
        raise UserError(f"{file} does not match ResNet-18 (torchvision layout): {what}")
    encoder.load_state_dict(state)
    return len(state)
