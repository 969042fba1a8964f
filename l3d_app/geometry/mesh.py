"""Triangle meshes: one small dataclass with optional per-vertex colours or a UV texture.

Units are world units; colours and textures are float in [0, 1]. UV coordinates follow
the OBJ convention (u to the right, v UP from the bottom of the texture image); the
texture image is stored top row first, (Ht, Wt, 3), as any image.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Optional

import torch

from l3d_app.errors import UserError


@dataclass
class Mesh:
    """A single triangle mesh.

    Attributes:
        verts: (V, 3) float vertex positions.
        faces: (F, 3) long vertex indices, counter-clockwise seen from outside.
        vert_colors: optional (V, 3) per-vertex RGB in [0, 1].
        verts_uvs: optional (T, 2) texture coordinates in [0, 1] (v up).
        faces_uvs: optional (F, 3) long indices into ``verts_uvs`` (lets UV seams exist
            without splitting vertices).
        texture: optional (Ht, Wt, 3) RGB image in [0, 1], top row first.
    """

    verts: torch.Tensor
    faces: torch.Tensor
    vert_colors: Optional[torch.Tensor] = None
    verts_uvs: Optional[torch.Tensor] = None
    faces_uvs: Optional[torch.Tensor] = None
    texture: Optional[torch.Tensor] = None

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        """Raise :class:`UserError` if shapes or indices are inconsistent."""
        v, f = self.verts, self.faces
        if v.dim() != 2 or v.shape[-1] != 3:
            raise UserError(f"mesh vertices must be (V, 3), got {tuple(v.shape)}")
        if f.dim() != 2 or f.shape[-1] != 3:
            raise UserError(f"mesh faces must be (F, 3) triangles, got {tuple(f.shape)}")
        if f.dtype not in (torch.int64, torch.int32):
            raise UserError(f"mesh faces must be integer indices, got {f.dtype}")
        if f.numel() and (int(f.min()) < 0 or int(f.max()) >= v.shape[0]):
            raise UserError(f"mesh face indices out of range [0, {v.shape[0]})")
        if not torch.isfinite(v).all():
            raise UserError("mesh vertices contain NaN or Inf")
        if self.vert_colors is not None and self.vert_colors.shape != v.shape:
            raise UserError(f"vert_colors must be (V, 3) = {tuple(v.shape)}, got {tuple(self.vert_colors.shape)}")
        has_uv = [x is not None for x in (self.verts_uvs, self.faces_uvs, self.texture)]
        if any(has_uv) and not all(has_uv):
            raise UserError("a UV texture needs verts_uvs, faces_uvs and texture together")
        if all(has_uv):
            if self.faces_uvs.shape != f.shape:
                raise UserError("faces_uvs must have the same shape as faces")
            if self.faces_uvs.numel() and int(self.faces_uvs.max()) >= self.verts_uvs.shape[0]:
                raise UserError("faces_uvs index out of range of verts_uvs")
            if self.texture.dim() != 3 or self.texture.shape[-1] != 3:
                raise UserError(f"texture must be (Ht, Wt, 3), got {tuple(self.texture.shape)}")

    # ------------------------------------------------------------ properties
    @property
    def num_verts(self) -> int:
        return self.verts.shape[0]

    @property
    def num_faces(self) -> int:
        return self.faces.shape[0]

    @property
    def device(self) -> torch.device:
        return self.verts.device

    @property
    def has_texture(self) -> bool:
        return self.texture is not None

    def to(self, device=None, dtype=None) -> "Mesh":
        """Move tensors; ``dtype`` applies to float tensors only."""
        out = {}
        for fld in fields(self):
            value = getattr(self, fld.name)
            if torch.is_tensor(value):
                value = value.to(device=device, dtype=dtype if value.is_floating_point() else None)
            out[fld.name] = value
        return Mesh(**out)

    def with_verts(self, verts: torch.Tensor) -> "Mesh":
        """Same topology and appearance, new (V, 3) vertex positions (keeps autograd)."""
        return replace(self, verts=verts)

    # ------------------------------------------------------------ geometry
    def face_verts(self) -> torch.Tensor:
        """(F, 3, 3) the three vertex positions of each face."""
        return self.verts[self.faces]

    def face_normals(self, unit: bool = True) -> torch.Tensor:
        """(F, 3) face normals (right-hand rule); area-weighted (length = 2 * area) if not unit.

        Degenerate faces give a zero vector, never NaN.
        """
        fv = self.face_verts()
        n = torch.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0], dim=-1)
        return torch.nn.functional.normalize(n, dim=-1, eps=1e-20) if unit else n

    def face_areas(self) -> torch.Tensor:
        """(F,) triangle areas."""
        return 0.5 * self.face_normals(unit=False).norm(dim=-1)

    def vertex_normals(self) -> torch.Tensor:
        """(V, 3) unit vertex normals: area-weighted sum of adjacent face normals."""
        n = self.face_normals(unit=False)
        acc = torch.zeros_like(self.verts).index_add_(0, self.faces.reshape(-1), n.repeat_interleave(3, dim=0))
        return torch.nn.functional.normalize(acc, dim=-1, eps=1e-20)

    def bounds(self):
        """(min (3,), max (3,)) of the vertices."""
        return self.verts.min(dim=0).values, self.verts.max(dim=0).values

    def normalized(self, radius: float = 1.0) -> "Mesh":
        """Centred at its bounding-box centre and scaled so the farthest vertex is at ``radius``."""
        lo, hi = self.bounds()
        centred = self.verts - (lo + hi) / 2
        scale = centred.norm(dim=-1).max().clamp_min(1e-12)
        return self.with_verts(centred * (radius / scale))

