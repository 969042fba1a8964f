"""Uniform random points on a triangle mesh surface (area-weighted, differentiable).

A sample is drawn in two steps:

1. a face, chosen with probability proportional to its area (``torch.multinomial`` over
   the face areas, with replacement; the choice is discrete and carries no gradient);
2. a point uniform inside that face, from the square-root trick: with ``r1, r2 ~ U(0, 1)``
   and ``s = sqrt(r1)`` the barycentric weights ``(1 - s, s (1 - r2), s r2)`` are uniform
   over the triangle (Osada et al. 2002, "Shape distributions", eq. 1).

Positions are barycentric combinations of the face's vertices, so they are differentiable
with respect to ``mesh.verts`` (``d point / d vert_j = w_j * I``). Degenerate (zero-area)
faces have zero probability and never receive a sample; a mesh without any face of positive
area raises :class:`~l3d_app.errors.UserError`.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.textures import sample_texture
from l3d_app.runtime.random import draw_device, rand

# Faces with area <= _REL_DEGENERATE * (largest face area) count as degenerate: this only
# absorbs round-off in the cross product of (nearly) collinear edges.
_REL_DEGENERATE = 1e-12


class SurfaceSamples(NamedTuple):
    """Samples on a mesh and where they come from.

    Attributes:
        points: (S, 3) positions, world units (differentiable w.r.t. the mesh vertices).
        face_index: (S,) long index of the face each sample lies on.
        barycentrics: (S, 3) weights of the face's three vertices (non-negative, sum 1).
    """

    points: torch.Tensor
    face_index: torch.Tensor
    barycentrics: torch.Tensor


def uniform_barycentrics(num_samples: int, generator: Optional[torch.Generator] = None,
                         device=None, dtype=torch.float32) -> torch.Tensor:
    """(S, 3) barycentric weights uniformly distributed over a triangle (square-root trick)."""
    r = rand((num_samples, 2), generator, device, dtype)
    s = r[:, 0].sqrt()
    return torch.stack([1 - s, s * (1 - r[:, 1]), s * r[:, 1]], dim=-1)


def sampling_weights(mesh: Mesh) -> torch.Tensor:
    """(F,) float64 face-selection weights: the face areas, exactly 0 for degenerate faces.

    Raises:
        UserError: if the mesh has no face of positive area.
    """
    if mesh.num_faces == 0:
        raise UserError("cannot sample points on a mesh with no faces")
    with torch.no_grad():
        fv = mesh.face_verts().to(torch.float64)
        areas = 0.5 * torch.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0], dim=-1).norm(dim=-1)
    largest = float(areas.max())
    if not largest > 0:
        raise UserError(f"cannot sample points on a mesh whose {mesh.num_faces} faces all have zero area")
    return torch.where(areas > _REL_DEGENERATE * largest, areas, torch.zeros_like(areas))


def sample_surface(mesh: Mesh, num_samples: int,
                   generator: Optional[torch.Generator] = None) -> SurfaceSamples:
    """Draw ``num_samples`` points uniformly (per unit area) on the surface of ``mesh``.

    Args:
        mesh: the triangle mesh; ``mesh.verts`` may require grad.
        num_samples: S >= 0, the number of points.
        generator: optional ``torch.Generator`` on the mesh's device; the same generator
            state gives the same faces and barycentrics.
    Returns:
        :class:`SurfaceSamples` (points (S, 3), face_index (S,), barycentrics (S, 3)).
    Raises:
        UserError: negative ``num_samples``, or no face of positive area.
    """
    if int(num_samples) != num_samples or num_samples < 0:
        raise UserError(f"num_samples must be a non-negative integer, got {num_samples}")
    num_samples = int(num_samples)
    weights = sampling_weights(mesh)
    device = mesh.device
    if num_samples == 0:
        face_index = torch.zeros(0, dtype=torch.long, device=device)
    else:
        face_index = torch.multinomial(weights.to(draw_device(generator, device)), num_samples, replacement=True,
                                       generator=generator).to(device)
    bary = uniform_barycentrics(num_samples, generator, device=device, dtype=mesh.verts.dtype)
    fv = mesh.verts[mesh.faces[face_index]]  # (S, 3, 3): gather keeps the graph to verts
    points = (bary.unsqueeze(-1) * fv).sum(dim=1)
    return SurfaceSamples(points, face_index, bary)


def _interpolate(values: torch.Tensor, faces: torch.Tensor, face_index: torch.Tensor,
                 bary: torch.Tensor) -> torch.Tensor:
    """Barycentric interpolation of per-vertex ``values`` (V, C) at the samples -> (S, C)."""
    return (bary.unsqueeze(-1) * values[faces[face_index]]).sum(dim=1)


def sample_colors(mesh: Mesh, samples: SurfaceSamples) -> torch.Tensor:
    """(S, 3) colours in [0, 1] at the samples: the UV texture (bilinear) when the mesh has
    one, else the interpolated vertex colours.

    Raises:
        UserError: if the mesh has neither a texture nor vertex colours.
    """
    if mesh.has_texture:
        uv = _interpolate(mesh.verts_uvs, mesh.faces_uvs, samples.face_index, samples.barycentrics)
        return sample_texture(mesh.texture, uv.to(mesh.texture.dtype))
    if mesh.vert_colors is not None:
        return _interpolate(mesh.vert_colors, mesh.faces, samples.face_index, samples.barycentrics)
    raise UserError("return_colors=True needs a mesh with vertex colours or a UV texture")


def sample_points_on_mesh(mesh: Mesh, num_samples: int, generator: Optional[torch.Generator] = None,
                          return_normals: bool = False, return_colors: bool = False) -> PointCloud:
    """Uniform random points on the surface of ``mesh``, as a :class:`PointCloud`.

    Args:
        mesh: triangle mesh (world units); gradients flow from the points to ``mesh.verts``.
        num_samples: S, number of points.
        generator: optional ``torch.Generator`` (on the mesh's device) for reproducibility.
        return_normals: fill ``normals`` with the unit geometric normal (right-hand rule)
            of each sample's face.
        return_colors: fill ``colors`` (S, 3) from the UV texture or the vertex colours
            (see :func:`sample_colors`).
    Returns:
        PointCloud with points (S, 3) and, as asked, normals (S, 3) and colors (S, 3).
        Use :func:`sample_surface` for the face indices and barycentrics as well.
    Raises:
        UserError: bad ``num_samples``, no face of positive area, or colours asked of a
            mesh that has none.
    """
    samples = sample_surface(mesh, num_samples, generator)
    normals = mesh.face_normals(unit=True)[samples.face_index] if return_normals else None
    colors = sample_colors(mesh, samples) if return_colors else None
    return PointCloud(samples.points, colors=colors, normals=normals)
