"""Backdrops: procedural scenery placed behind a subject (for the dolly zoom)."""

from __future__ import annotations

import torch

from l3d_app.geometry.mesh import Mesh, concat_meshes
from l3d_app.geometry.primitives import cube


def pillar_backdrop(rows: int = 4, columns: int = 7, spacing: float = 2.5, first_depth: float = 3.0,
                    device=None) -> Mesh:
    """Rows of tall coloured pillars behind the origin (at negative Z), on a floor slab.

    Seen from the +Z axis they recede into the distance, so a change of perspective
    (the dolly zoom) is obvious. Units: world units; the floor is at y = -1.
    """
    colors = torch.tensor([[0.90, 0.35, 0.30], [0.30, 0.60, 0.90], [0.95, 0.80, 0.30],
                           [0.45, 0.80, 0.45]])
    unit = cube(size=1.0)
    parts = []
    for r in range(rows):  # a few dozen boxes: building the scene, not a hot path
        for c in range(columns):
            x = (c - (columns - 1) / 2) * spacing
            z = -(first_depth + r * spacing)
            scale = torch.tensor([0.6, 3.0, 0.6])
            offset = torch.tensor([x, 0.5, z])
            color = colors[(r + c) % len(colors)].expand(unit.num_verts, 3)
            parts.append(Mesh(unit.verts * scale + offset, unit.faces, vert_colors=color))
    depth = first_depth + rows * spacing
    floor_scale = torch.tensor([columns * spacing + 20.0, 0.1, depth + 20.0])
    floor_offset = torch.tensor([0.0, -1.05, -depth / 2])
    parts.append(Mesh(unit.verts * floor_scale + floor_offset, unit.faces,
                      vert_colors=torch.full((unit.num_verts, 3), 0.85)))
    return concat_meshes(parts).to(device)
