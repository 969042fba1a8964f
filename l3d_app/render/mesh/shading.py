"""Shading: attribute interpolation and Lambert / Phong lighting (textures: ``textures.py``).

Layout: the lighting functions take CHANNELS-FIRST packed tensors, (3, P) for P shaded
points (or anything broadcastable, e.g. a (3, 1) constant), because on the CPU each
channel as one contiguous row is several times faster than (P, 3) rows of three.

All colours are linear RGB floats in [0, 1] (lit colours are not clamped here). Directions
are world-space. Reflection model, per light with colour ``c_l`` and unit direction ``l``
FROM the surface TOWARDS the light:

    rgb = albedo * (mat.ambient * lights.ambient + mat.diffuse * sum_l c_l * max(n.l, 0))
          + mat.specular * sum_l c_l * max(r.v, 0) ** mat.shininess   [only where n.l > 0]

with ``r = 2 (n.l) n - l`` the mirrored light direction and ``v`` the unit direction from
the surface to the camera centre: the classic Phong model (as PyTorch3D), not Blinn-Phong.
Point lights have no distance attenuation. Normals are not flipped towards the camera
(one-sided lighting): the inside of an open mesh is lit as its outside.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Sequence, Tuple, Union

import torch

from l3d_app.render.mesh.rasterize import Fragments

Color = Union[float, Sequence[float], torch.Tensor]


def _column(x, like: torch.Tensor) -> torch.Tensor:
    """(3, 1) from a scalar / 3 numbers / (3,) tensor; a (3, P) tensor is returned as is."""
    t = torch.as_tensor(x, dtype=like.dtype, device=like.device)
    if t.dim() == 2:
        return t
    t = t.reshape(-1)
    return (t.expand(3) if t.numel() == 1 else t).reshape(3, 1)


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Channel-first dot product: (3, ...) x (3, ...) -> (...)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def normalize(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit vectors along dim 0 of a channel-first (3, ...) tensor (zero stays zero)."""
    return x * torch.rsqrt(dot(x, x).clamp_min(eps * eps))


@dataclass
class Lights:
    """Light sources (world space).

    Attributes:
        ambient: ambient light colour (3,) or scalar.
        directional: list of ``(direction, colour)``; ``direction`` (3,) points from the
            surface TOWARDS the light (PyTorch3D's convention), need not be unit length;
            a channel-first (3, P) tensor gives one direction per shaded point.
        point: list of ``(position, colour)``; ``position`` (3,) world units.
    """

    ambient: Color = (1.0, 1.0, 1.0)
    directional: List[Tuple[Color, Color]] = field(default_factory=list)
    point: List[Tuple[Color, Color]] = field(default_factory=list)


@dataclass
class Material:
    """Reflectance: ambient/diffuse/specular colours (3,) or scalars; shininess (Phong exponent)."""

    ambient: Color = 0.4
    diffuse: Color = 0.6
    specular: Color = 0.2
    shininess: float = 32.0


# ------------------------------------------------------------------ interpolation
def interpolate_packed(faces: torch.Tensor, bary: torch.Tensor, face_attributes: torch.Tensor
                       ) -> torch.Tensor:
    """Per-pixel attributes (P, C) from face indices (P,), barycentrics (P, 3) and
    per-face-vertex attributes (F, 3, C)."""
    n_faces, _, C = face_attributes.shape
    corner = face_attributes.reshape(n_faces, 3 * C).index_select(0, faces).view(-1, 3, C)
    return torch.bmm(bary[:, None, :].to(corner.dtype), corner)[:, 0]


def interpolate_vertices(table: torch.Tensor, corner_index: Sequence[torch.Tensor],
                         bary_t: torch.Tensor) -> torch.Tensor:
    """Channel-first interpolation of per-vertex attributes.

    Args:
        table: (C, V) attribute of each vertex (channels first).
        corner_index: three (P,) long tensors, the vertex index of each face corner.
        bary_t: (3, P) barycentrics, one row per corner.
    Returns:
        (C, P).
    """
    out = table.index_select(1, corner_index[0]) * bary_t[0]
    out.addcmul_(table.index_select(1, corner_index[1]), bary_t[1])
    return out.addcmul_(table.index_select(1, corner_index[2]), bary_t[2])


def interpolate(fragments: Fragments, face_attributes: torch.Tensor) -> torch.Tensor:
    """(B, H, W, C) attributes interpolated with the perspective-correct barycentrics.

    ``face_attributes`` (F, 3, C), e.g. ``vert_colors[faces]``. Background pixels get 0.
    """
    return fragments.densify(interpolate_packed(fragments.fg_faces, fragments.fg_bary,
                                                face_attributes))


# ------------------------------------------------------------------ lighting
def phong(points: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor,
          eye: torch.Tensor, lights: Lights, material: Material,
          specular: bool = True) -> torch.Tensor:
    """Phong (or, with ``specular=False``, Lambert) shading, channels first.

    Args:
        points: (3, P) world positions (used by point lights and the view vector).
        normals: (3, P) unit world normals.
        albedo: (3, P) or (3, 1) base colour.
        eye: (3, P) or (3,) camera centre seen by each point.
        lights, material: see the module docstring for the formula.
    Returns:
        (3, P) RGB.
    """
    ref = normals
    shape = torch.broadcast_shapes(normals.shape, points.shape)
    diffuse = normals.new_zeros(shape)
    spec = normals.new_zeros(shape)
    view = normalize(_column(eye, ref) - points) if specular else None
    dirs = [(normalize(_column(d, ref)), c) for d, c in lights.directional]
    dirs += [(normalize(_column(p, ref) - points), c) for p, c in lights.point]
    for ldir, c in dirs:
        col = _column(c, ref)
        cos = dot(normals, ldir)
        diffuse.addcmul_(cos.clamp_min(0)[None], col)
        if specular:
            refl = 2 * cos * normals - ldir
            rv = dot(refl, view).clamp_min_(0).pow_(float(material.shininess))
            spec.addcmul_((rv * (cos > 0))[None], col)
    light = _column(lights.ambient, ref) * _column(material.ambient, ref)
    rgb = (diffuse * _column(material.diffuse, ref)).add_(light).mul_(_column(albedo, ref))
    if specular:
        rgb.addcmul_(spec, _column(material.specular, ref))
    return rgb


def lambert(points: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor,
            lights: Lights, material: Material) -> torch.Tensor:
    """Lambert (ambient + diffuse) shading, (3, P); arguments as :func:`phong`."""
    return phong(points, normals, albedo, torch.zeros(3, dtype=normals.dtype,
                                                      device=normals.device),
                 lights, material, specular=False)
