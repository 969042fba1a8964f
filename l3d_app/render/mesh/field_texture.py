"""Mesh rendering with the albedo taken from a field of the surface point (e.g.
:class:`l3d_app.models.texture_field.TextureField`) instead of a UV texture or vertex colours."""

from __future__ import annotations

import torch

from l3d_app.geometry.mesh import Mesh
from l3d_app.render.mesh.renderer import MeshRenderer
from l3d_app.render.mesh.shading import interpolate_vertices


class FieldTextureRenderer(MeshRenderer):
    """:class:`MeshRenderer` whose albedo is ``field(surface point)`` at each covered pixel.

    Differentiable w.r.t. the field's parameters (not the geometry or the visibility).
    """

    def __init__(self, field: torch.nn.Module, **kwargs):
        super().__init__(**kwargs)
        self.field = field

    def albedo(self, mesh: Mesh, faces, corners, bary_t: torch.Tensor) -> torch.Tensor:
        points = interpolate_vertices(mesh.verts.t().to(bary_t.dtype), corners, bary_t)  # (3, P)
        return self.field(points.t()).t()
