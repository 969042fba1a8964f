"""Built-in mesh scenes and the mesh-file data source (``data=builtin`` / ``data=mesh``).

World frame: +Y up, right-handed; a camera on +Z looking at the origin sees +X to its
right. The default scene, :func:`orientation_scene`, makes that frame unmistakable in a
turntable: a red arrow along +X, a green one along +Y, a blue one along +Z, a grey ball
at the origin, a yellow letter "F" (no mirror or rotation symmetry: it reads correctly
only from the +Z side) standing on a white pedestal.
"""

from __future__ import annotations

from typing import Callable, Dict

import torch

from l3d_app.errors import UserError
from l3d_app.geometry import primitives as P
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.mesh_io import load_mesh
from l3d_app.registry import DATASETS
from l3d_app.runtime.paths import resolve_path

RED, GREEN, BLUE = (0.90, 0.10, 0.10), (0.10, 0.75, 0.15), (0.10, 0.25, 0.95)
YELLOW, WHITE, GREY = (0.95, 0.80, 0.10), (0.92, 0.92, 0.88), (0.60, 0.60, 0.60)

# Proper rotations taking +Y to each axis (column vectors).
_Y_TO = {
    "x": torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    "y": torch.eye(3),
    "z": torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
}


def arrow(axis: str, color, length: float = 0.78, radius: float = 0.03, n: int = 32) -> Mesh:
    """Closed arrow from the origin along +``axis`` (``x``, ``y`` or ``z``): shaft + cone head."""
    head = 0.24 * length
    shaft = P.transformed(P.cylinder(radius, length - head, n, color), translation=(0, (length - head) / 2, 0))
    tip = P.transformed(P.cone(2.6 * radius, head, n, color), translation=(0, length - head / 2, 0))
    return P.transformed(P.join([shaft, tip]), rotation=_Y_TO[axis])


def letter_f(color=YELLOW, z: float = -0.30) -> Mesh:
    """A block letter "F" in the plane z = ``z``, reading correctly from +Z, standing on y = -0.58."""
    depth = 0.08
    parts = [((-0.52, -0.28), (0.10, 0.60)),   # stem
             ((-0.41, -0.03), (0.32, 0.10)),   # top bar
             ((-0.445, -0.24), (0.25, 0.09))]  # middle bar
    return P.join([P.box((x, y, z), (w, h, depth), color) for (x, y), (w, h) in parts])


def orientation_scene() -> Mesh:
    """The default scene: one vertex-coloured mesh of closed parts (2276 faces), radius < 1, +Y up."""
    pedestal = P.transformed(P.cylinder(0.72, 0.08, 96, WHITE), translation=(0, -0.62, 0))
    return P.join([pedestal, P.icosphere(3, 0.09, GREY), arrow("x", RED), arrow("y", GREEN),
                   arrow("z", BLUE), letter_f()])


def position_colors(mesh: Mesh) -> Mesh:
    """Same mesh with vertex colours ``0.5 + 0.5 * p / max|p|`` (direction shows as colour)."""
    v = mesh.verts
    return Mesh(verts=v, faces=mesh.faces,
                vert_colors=(0.5 + 0.5 * v / v.norm(dim=-1).max().clamp_min(1e-12)).clamp(0, 1))


SCENES: Dict[str, Callable[[], Mesh]] = {
    "orientation": orientation_scene,
    "cube": lambda: position_colors(P.cube(1.0)),
    "icosphere": lambda: position_colors(P.icosphere(3, 1.0)),
    "torus": lambda: position_colors(P.torus(0.7, 0.3, 48, 24)),
    "tetrahedron": lambda: position_colors(P.tetrahedron(1.0)),
}


@DATASETS.register("builtin")
def builtin_scene(scene: str = "orientation", normalize: bool = False, device=None) -> Mesh:
    """A built-in procedural mesh by name (see ``SCENES``); ``normalize`` fits it to the unit sphere."""
    if scene not in SCENES:
        raise UserError(f"unknown built-in scene '{scene}'. Known: {', '.join(sorted(SCENES))}")
    mesh = SCENES[scene]()
    if normalize:
        mesh = mesh.normalized(1.0)
    return mesh if device is None else mesh.to(device)


@DATASETS.register("mesh")
def mesh_file(path: str = None, keep_vertex_order: bool = True, normalize: bool = True, device=None) -> Mesh:
    """A user's mesh file (OBJ/PLY/GLB/GLTF/OFF/STL); ``normalize`` centres it and scales
    its farthest vertex to radius 1, so any mesh frames like the built-in scenes."""
    if path is None or not str(path).strip():
        raise UserError("data=mesh needs a file: add data.path=FILE "
                        "(.obj, .ply, .glb, .gltf, .off or .stl)")
    mesh = load_mesh(str(resolve_path(str(path).strip())), keep_vertex_order=keep_vertex_order)
    if normalize:
        mesh = mesh.normalized(1.0)
    return mesh if device is None else mesh.to(device)
