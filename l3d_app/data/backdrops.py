"""Backdrops: procedural scenery placed behind a subject (for the dolly zoom)."""

from __future__ import annotations

import torch

from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.primitives import cube, join, plane


def pillar_backdrop(rows: int = 4, columns: int = 7, spacing: float = 2.5, first_depth: float = 3.0,
                    device=None) -> Mesh:
    """Rows of tall coloured boxes behind the origin (at negative Z), on a floor plane.

    Seen from the +Z axis they recede into the distance, so a change of perspective
    (the dolly zoom) is obvious. Render it with flat shading (the boxes share vertices). Units: world units; the floor is at y = -1.
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
    # Subdivided: faces crossing the near plane are dropped whole by the rasteriser.
    floor = plane(size=1.0, n=32, color=(0.8, 0.8, 0.78))
    floor_scale = torch.tensor([columns * spacing + 40.0, 1.0, depth + 40.0])
    parts.append(floor.with_verts(floor.verts * floor_scale + torch.tensor([0.0, -1.0, -depth / 2])))
    return join(parts).to(device)
