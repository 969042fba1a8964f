"""Meshes of fields: marching cubes of a level set with optional vertex colours, saved as
PLY (vertex colours) and GLB (trimesh; vertex colours as COLOR_0)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Optional, Sequence, Tuple

import numpy as np
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.marching_cubes import evaluate_grid, sdf_to_mesh
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.mesh_io import save_mesh
from l3d_app.runtime.files import atomic_path

ColorFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@torch.no_grad()
def extract_mesh(level_fn: Callable[[torch.Tensor], torch.Tensor], box: Tuple[Sequence[float], Sequence[float]],
                 resolution: int = 128, level: float = 0.0, color_fn: Optional[ColorFn] = None,
                 device=None) -> Optional[Mesh]:
    """Mesh of ``{p : level_fn(p) = level}`` (``level_fn`` (N, 3) -> (N,), positive outside,
    e.g. an SDF or minus a density) over ``box``; None when the level set does not cross the grid.

    ``color_fn(points (V, 3), outward normals (V, 3)) -> rgb (V, 3)`` colours the vertices
    (e.g. a radiance field looking along ``-normal``); clamped to [0, 1].
    """
    try:
        mesh = sdf_to_mesh(_on_grid(level_fn), resolution=int(resolution), bounds=(list(box[0]), list(box[1])),
                           level=float(level), colors=None, device=device)
    except UserError:
        return None
    if color_fn is not None:
        rgb = color_fn(mesh.verts, mesh.vertex_normals()).clamp(0, 1)
        mesh = Mesh(verts=mesh.verts, faces=mesh.faces, vert_colors=rgb)
    return mesh


def _on_grid(level_fn: Callable[[torch.Tensor], torch.Tensor]) -> Callable[[torch.Tensor], torch.Tensor]:
    """``level_fn`` ((N, 3) -> (N,)) on points of any leading shape (..., 3) -> (...)."""
    return lambda p: level_fn(p.reshape(-1, 3)).reshape(p.shape[:-1])


PROBE_RESOLUTION = 64    # the grid timed to price a level function per point: 262,144 points


@torch.no_grad()
def seconds_per_grid_point(level_fn: Callable[[torch.Tensor], torch.Tensor], box, resolution: int = PROBE_RESOLUTION,
                           device=None) -> float:
    """Wall seconds per point of ``level_fn`` ((N, 3) -> (N,)) evaluated as :func:`extract_mesh` evaluates
    it, measured once on a ``resolution``^3 grid over ``box`` ((lo, hi), world units): what
    :meth:`~l3d_app.runtime.budget.TimeBudget.keep_mesh` prices a mesh at another resolution with."""
    start = time.perf_counter()
    evaluate_grid(_on_grid(level_fn), list(box[0]), list(box[1]), int(resolution), device=device)
    return (time.perf_counter() - start) / int(resolution) ** 3


def save_glb(mesh: Mesh, path) -> Path:
    """Write ``mesh`` (with its vertex colours, if any) as binary glTF through trimesh."""
    import trimesh

    colors = None
    if getattr(mesh, "vert_colors", None) is not None:
        colors = (mesh.vert_colors.detach().cpu().clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    tm = trimesh.Trimesh(mesh.verts.detach().cpu().numpy(), mesh.faces.detach().cpu().numpy(),
                         vertex_colors=colors, process=False)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(tm.export(file_type="glb"))
    return Path(path)


FIELD_MESH_FORMATS = ("ply", "obj", "glb")


def save_field_mesh(mesh: Mesh, stem, formats: Sequence[str] = ("ply", "glb")) -> list:
    """Write ``stem.<fmt>`` for each of ``formats`` (ply | obj | glb); returns the paths."""
    paths = []
    for fmt in formats:
        fmt = str(fmt).lower().lstrip(".")
        if fmt not in FIELD_MESH_FORMATS:
            raise UserError(f"mesh format must be ply, obj or glb, got {fmt!r}")
        path = Path(f"{stem}.{fmt}")
        paths.append(save_glb(mesh, path) if fmt == "glb" else save_mesh(mesh, path))
    return paths
