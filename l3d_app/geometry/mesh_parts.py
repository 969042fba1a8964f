"""Connected parts of a triangle mesh: labels, the largest part, and sub-meshes.

Two faces belong to the same part when they share a vertex (index, not position: a mesh
whose seams are split into duplicate vertices counts the pieces as separate parts).
"""

from __future__ import annotations

import torch

from l3d_app.geometry.mesh import Mesh


def face_components(faces: torch.Tensor, num_verts: int) -> torch.Tensor:
    """(F,) long part label per face: the smallest vertex index of its connected part.

    Vectorised label propagation: each vertex takes the minimum label of the faces it
    touches (``scatter_reduce`` amin), then pointer jumping ``label = label[label]``;
    repeated until nothing changes (a few dozen passes on meshes of 10^5 faces).
    """
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces must be (F, 3), got {tuple(faces.shape)}")
    labels = torch.arange(int(num_verts), device=faces.device)
    flat = faces.reshape(-1)
    while True:
        face_min = labels[faces].amin(dim=1)                                  # (F,)
        new = labels.scatter_reduce(0, flat, face_min.repeat_interleave(3), reduce="amin")
        new = new[new]                                                        # pointer jumping
        if torch.equal(new, labels):
            return labels[faces[:, 0]]
        labels = new


def largest_part_mask(mesh: Mesh) -> torch.Tensor:
    """(F,) bool mask of the faces of the part with the most faces (ties: smallest label)."""
    labels = face_components(mesh.faces, mesh.num_verts)
    values, counts = torch.unique(labels, return_counts=True)
    return labels == values[torch.argmax(counts)]


def submesh(mesh: Mesh, face_mask: torch.Tensor) -> Mesh:
    """The faces selected by ``face_mask`` (F,) bool, with only the vertices they use
    (re-indexed in their original order); colours, UVs and texture follow."""
    if face_mask.shape != (mesh.num_faces,) or face_mask.dtype != torch.bool:
        raise ValueError(f"face_mask must be a ({mesh.num_faces},) bool tensor")
    faces = mesh.faces[face_mask]
    used = torch.zeros(mesh.num_verts, dtype=torch.bool, device=mesh.faces.device)
    used[faces.reshape(-1)] = True
    remap = torch.cumsum(used.long(), 0) - 1
    return Mesh(verts=mesh.verts[used], faces=remap[faces],
                vert_colors=None if mesh.vert_colors is None else mesh.vert_colors[used],
                verts_uvs=mesh.verts_uvs,
                faces_uvs=None if mesh.faces_uvs is None else mesh.faces_uvs[face_mask],
                texture=mesh.texture)
