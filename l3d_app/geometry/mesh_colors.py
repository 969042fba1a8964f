"""Re-texturing: replace a mesh's appearance by per-vertex colours."""

from __future__ import annotations

from typing import Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh

_AXES = {"x": 0, "y": 1, "z": 2}


def gradient_colors(mesh: Mesh, axis: str = "z", color1: Sequence[float] = (0.0, 0.0, 1.0),
                    color2: Sequence[float] = (1.0, 0.0, 0.0)) -> Mesh:
    """Colour vertices by a linear blend along ``axis``: ``color1`` at the smallest
    coordinate, ``color2`` at the largest, ``alpha = (c - c_min) / (c_max - c_min)``.

    Any UV texture is dropped. A mesh flat along ``axis`` gets ``color1`` everywhere.
    """
    if axis not in _AXES:
        raise UserError(f"retexture axis must be one of x, y, z, got {axis!r}")
    c1, c2 = (torch.as_tensor(c, dtype=mesh.verts.dtype, device=mesh.device) for c in (color1, color2))
    if c1.shape != (3,) or c2.shape != (3,):
        raise UserError("retexture colours must be [r, g, b] triples")
    coord = mesh.verts[:, _AXES[axis]].detach()
    span = (coord.max() - coord.min()).clamp_min(1e-12)
    alpha = ((coord - coord.min()) / span)[:, None]
    return Mesh(mesh.verts, mesh.faces, vert_colors=(1 - alpha) * c1 + alpha * c2)
