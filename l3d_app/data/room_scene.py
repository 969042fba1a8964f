"""A built-in room as a point cloud: floor, three walls and furniture (``data=room``).

The room is 4 x 4 units with walls 2.5 high (floor at y = 0, +Y up, open towards +Z): a floor,
back (z = -2), left (x = -2) and right (x = +2) walls, a table (top at y = 0.75, four legs),
a cabinet against the back wall and a ball on the table. Points are drawn area-uniformly
(:func:`l3d_app.geometry.sampling.sample_points_on_mesh`) with each face's true normal and
the part's colour; optional Gaussian noise (``noise``, world units) moves them off the
surfaces. Horizontal surfaces: floor, table top, cabinet top, the boxes' undersides; vertical:
walls and the boxes' sides; neither: most of the ball.
"""

from __future__ import annotations

from typing import Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.primitives import box, icosphere, join, transformed
from l3d_app.geometry.sampling import sample_points_on_mesh
from l3d_app.registry import DATASETS

ROOM_SIZE, WALL_HEIGHT = 4.0, 2.5


def rectangle(origin: Sequence[float], u: Sequence[float], v: Sequence[float], color, cells: int = 4) -> Mesh:
    """The flat rectangle ``origin + a u + b v`` (a, b in [0, 1]) as a ``cells`` x ``cells`` grid of
    quads (2 triangles each), normal along ``u x v``, one colour."""
    o, u, v = (torch.as_tensor(x, dtype=torch.float32) for x in (origin, u, v))
    s = torch.linspace(0, 1, cells + 1)
    a, b = torch.meshgrid(s, s, indexing="ij")
    verts = o + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    i = torch.arange(cells).repeat_interleave(cells)
    j = torch.arange(cells).repeat(cells)
    p00, p10, p01, p11 = i * (cells + 1) + j, (i + 1) * (cells + 1) + j, i * (cells + 1) + j + 1, \
        (i + 1) * (cells + 1) + j + 1
    faces = torch.cat([torch.stack([p00, p10, p11], 1), torch.stack([p00, p11, p01], 1)])
    return Mesh(verts=verts, faces=faces, vert_colors=torch.tensor(color, dtype=torch.float32).expand_as(verts).clone())


def room_mesh() -> Mesh:
    """The room's surfaces as one mesh (world units, floor at y = 0)."""
    h, r = WALL_HEIGHT, ROOM_SIZE / 2
    parts = [
        rectangle((-r, 0, -r), (0, 0, 2 * r), (2 * r, 0, 0), (0.60, 0.50, 0.40)),   # floor, normal +Y
        rectangle((-r, 0, -r), (2 * r, 0, 0), (0, h, 0), (0.85, 0.85, 0.80)),       # back wall, +Z
        rectangle((-r, 0, -r), (0, h, 0), (0, 0, 2 * r), (0.80, 0.85, 0.85)),       # left wall, +X
        rectangle((r, 0, -r), (0, 0, 2 * r), (0, h, 0), (0.85, 0.80, 0.85)),        # right wall, -X
        box((-0.3, 0.72, 0.0), (1.2, 0.06, 0.8), color=(0.55, 0.35, 0.20)),        # table top
        box((1.2, 0.6, -1.7), (0.8, 1.2, 0.5), color=(0.30, 0.40, 0.60)),          # cabinet
        transformed(icosphere(2, 0.2, color=(0.85, 0.25, 0.25)), translation=(-0.2, 0.95, 0.0)),  # ball
    ]
    for x in (-0.85, 0.25):
        for z in (-0.35, 0.35):
            parts.append(box((x, 0.345, z), (0.06, 0.69, 0.06), color=(0.45, 0.30, 0.15)))  # legs
    return join(parts)


@DATASETS.register("room")
def room_points(num_samples: int = 20000, noise: float = 0.0, seed: int = 0, device=None) -> PointCloud:
    """``num_samples`` points on :func:`room_mesh` with true normals and colours, plus N(0, noise^2)
    per coordinate; drawn on the CPU from ``seed``, then moved to ``device``."""
    if int(num_samples) < 3:
        raise UserError(f"the room needs num_samples >= 3, got {num_samples}")
    if not float(noise) >= 0:
        raise UserError(f"noise must be >= 0, got {noise}")
    gen = torch.Generator().manual_seed(int(seed))
    cloud = sample_points_on_mesh(room_mesh(), int(num_samples), gen, return_normals=True, return_colors=True)
    points = cloud.points + float(noise) * torch.randn(cloud.points.shape, generator=gen)
    return PointCloud(points.detach(), colors=cloud.colors, normals=cloud.normals).to(device=device)
