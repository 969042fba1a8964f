"""The course's box images: four 256x256 views of an SDF box with known cameras.

Files ``box_0.npy … box_3.npy`` (float32 (256, 256, 3) in [0, 1]) under ``root``; cameras
as stated in ``../shared/data/README.md`` (box/): PyTorch3D convention, NDC focal 1.0,
principal point (0, 0), looking at the origin with up (0, 1, 0) from the eyes in
:data:`BOX_EYES`. They enter the library through :func:`from_pytorch3d`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from l3d_app.data.array_files import load_array_file, numeric_array
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, from_pytorch3d, look_at_rotation
from l3d_app.registry import DATASETS

#: Camera centres (world units) of box_0 … box_3, from the course README.
BOX_EYES = ((-2.5, 0.0, 0.0), (-1.0, 0.0, -2.2), (0.0, 0.0, -2.5), (1.0, 0.0, -2.2))
BOX_IMAGE_SIZE = 256
_FLIP_XY = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))


@dataclass
class ImageSet:
    """Posed images: ``images`` (B, H, W, 3) float32 in [0, 1] and their ``cameras`` (B views)."""

    images: torch.Tensor
    cameras: Cameras

    def __len__(self) -> int:
        return self.images.shape[0]


def box_cameras(image_size: int = BOX_IMAGE_SIZE, device=None, dtype=torch.float32) -> Cameras:
    """The four box cameras (internal convention), built as PyTorch3D cameras and converted.

    PyTorch3D's ``look_at_view_transform`` gives ``R_p3d`` whose columns are the view axes
    (+X left, +Y up, +Z forward) in world coordinates and ``T = -eye @ R_p3d``.
    """
    eye = torch.tensor(BOX_EYES, dtype=torch.float64)
    at, up = torch.zeros_like(eye), torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    R_cv = look_at_rotation(eye, at, up)                      # rows: right, down, forward
    R_p3d = (_FLIP_XY @ R_cv).transpose(1, 2)                 # columns: left, up, forward
    T_p3d = -(eye[:, None, :] @ R_p3d)[:, 0]
    cams = from_pytorch3d(R_p3d, T_p3d, focal=1.0, principal_point=(0.0, 0.0),
                          image_size=(image_size, image_size), in_ndc=True)
    return cams.to(device=device, dtype=dtype)


@DATASETS.register("box")
def load_box_images(root: str, device: Optional[torch.device] = None) -> ImageSet:
    """Load ``root/box_{0..3}.npy`` and their cameras.

    ``root`` should be absolute (tasks resolve relative paths, see ``tasks/box.py``).
    Raises :class:`UserError` naming the path for a missing folder or file, and for an
    image that is not (256, 256, 3).
    """
    folder = Path(root)
    if not folder.is_dir():
        raise UserError(f"box data folder not found: {folder} (set data.root=DIR)")
    images = []
    for i in range(len(BOX_EYES)):
        path = folder / f"box_{i}.npy"
        if not path.is_file():
            raise UserError(f"box image missing: {path}")
        arr = load_array_file(path, allow_pickle=False)
        if arr.shape != (BOX_IMAGE_SIZE, BOX_IMAGE_SIZE, 3):
            raise UserError(f"box image {path} has shape {tuple(arr.shape)}, "
                            f"expected ({BOX_IMAGE_SIZE}, {BOX_IMAGE_SIZE}, 3)")
        arr = numeric_array(arr, f"box image {path}")
        if not np.isfinite(arr).all():
            raise UserError(f"box image {path} contains NaN or Inf")
        images.append(torch.from_numpy(arr))
    return ImageSet(torch.stack(images).to(device), box_cameras(device=device))
