"""RGB-D images <-> point clouds, and exact point-to-mesh distances.

Depth maps hold camera-frame Z (world units; the convention of
:mod:`l3d_app.geometry.cameras` and of ``MeshRenderer``'s ``depth``), with 0 (or any
value <= 0, or non-finite) meaning "no measurement". A pixel ``(i, j)`` with depth ``Z``
unprojects to ``C + Z * d`` where ``d`` is the ray through its centre ``(j + .5, i + .5)``
scaled to camera Z = 1 (:func:`l3d_app.geometry.rays.pixels_to_directions`).
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence, Tuple, Union

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.rays import pixel_centers, pixels_to_directions


def unproject_depth(depth: torch.Tensor, cams: Cameras, rgb: Optional[torch.Tensor] = None,
                    mask: Optional[torch.Tensor] = None) -> PointCloud:
    """World points of all valid pixels of B depth maps, as one cloud (views in order,
    pixels row-major).

    Args:
        depth: (B, H, W) camera Z in world units; <= 0 or non-finite = invalid.
        cams: B cameras of size H x W.
        rgb: optional (B, H, W, 3) colours in [0, 1] -> the cloud's colours.
        mask: optional (B, H, W) bool (or 0/1); False pixels are dropped.
    Returns:
        PointCloud with (P, 3) points (and (P, 3) colours when ``rgb`` is given).
    """
    if depth.dim() == 2:
        depth = depth[None]
    B, H, W = depth.shape
    if (cams.batch_size, cams.height, cams.width) != (B, H, W):
        raise UserError(f"depth {tuple(depth.shape)} does not match {cams.batch_size} cameras "
                        f"of {cams.height}x{cams.width}")
    if rgb is not None and rgb.shape[:3] != depth.shape:
        raise UserError(f"rgb {tuple(rgb.shape)} does not match depth {tuple(depth.shape)}")
    if mask is not None and mask.shape != depth.shape:
        raise UserError(f"mask {tuple(mask.shape)} does not match depth {tuple(depth.shape)}")
    cams = cams.to(device=depth.device, dtype=depth.dtype)
    valid = torch.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= mask.to(device=depth.device).bool()
    uv = pixel_centers(H, W, device=depth.device, dtype=depth.dtype)[None].expand(B, H, W, 2)
    dirs = pixels_to_directions(cams, uv, normalize=False)  # (B, H, W, 3), camera Z = 1
    centres = cams.centers()[:, None, None, :]
    points = (centres + depth.nan_to_num(0.0)[..., None] * dirs)[valid]
    colors = None if rgb is None else rgb.to(points.dtype)[valid]
    return PointCloud(points, colors)


def concat_clouds(clouds: Sequence[PointCloud]) -> PointCloud:
    """Union of clouds in one frame; colours/normals kept only if every cloud has them."""
    if not clouds:
        raise UserError("cannot concatenate an empty list of point clouds")
    cat = lambda name: (None if any(getattr(c, name) is None for c in clouds)  # noqa: E731
                        else torch.cat([getattr(c, name) for c in clouds]))
    return PointCloud(torch.cat([c.points for c in clouds]), cat("colors"), cat("normals"))


def unproject_views(depth: Union[torch.Tensor, Sequence[torch.Tensor]],
                    cams: Union[Cameras, Sequence[Cameras]],
                    rgb=None, mask=None) -> PointCloud:
    """Union, in the world frame, of the clouds of several RGB-D views.

    ``depth`` (B, H, W) with B cameras, or lists (one entry per batch, image sizes may
    differ) of depth / Cameras / rgb / mask as in :func:`unproject_depth`.
    """
    if torch.is_tensor(depth):
        return unproject_depth(depth, cams, rgb, mask)
    n = len(depth)
    if isinstance(cams, Cameras) or len(cams) != n:
        raise UserError("unproject_views with a list of depth maps needs a list of cameras of the same length")
    rgb = [None] * n if rgb is None else rgb
    mask = [None] * n if mask is None else mask
    return concat_clouds([unproject_depth(d, c, r, m) for d, c, r, m in zip(depth, cams, rgb, mask)])


def rgbd_from_mesh(mesh: Mesh, cams: Cameras, renderer=None) -> Dict[str, torch.Tensor]:
    """Render RGB-D views of a mesh: rgb (B, H, W, 3) albedo, depth (B, H, W) camera Z
    (0 on background), mask (B, H, W) bool. ``renderer`` defaults to an unlit
    ``MeshRenderer`` (colours = albedo); supersampling is refused (it blurs depth)."""
    from l3d_app.render.mesh_renderer import MeshRenderer  # render -> geometry; keep lazy

    renderer = renderer or MeshRenderer(shading="unlit")
    if getattr(renderer, "antialias", 1) != 1:
        raise UserError("rgbd_from_mesh needs antialias=1: averaged depths lie off the surface")
    out = renderer(mesh, cams)
    mask = out["alpha"] > 0.5
    return {"rgb": out["image"], "depth": torch.where(mask, out["depth"], 0.0), "mask": mask}


# ----------------------------------------------------------- point to mesh distance
def _closest_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
                          ) -> torch.Tensor:
    """Barycentrics (..., 3) of the closest point to ``p`` on triangles (a, b, c), all
    broadcastable (..., 3). The best of four candidates: the projection onto the plane
    when it falls inside a non-degenerate triangle, and the closest point of each edge
    (segments; a zero-length edge gives its end point), so degenerate triangles are exact
    too."""
    dot = lambda x, y: (x * y).sum(-1)  # noqa: E731
    safe = lambda d: torch.where(d > 0, d, torch.ones_like(d))  # noqa: E731
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2  # Ericson 5.1.5
    denom = va + vb + vc  # = |ab x ac|^2 >= 0
    inside = (va >= 0) & (vb >= 0) & (vc >= 0) & (denom > 0)
    z = torch.zeros_like(d1)
    best_b = torch.stack([va, vb, vc], -1) / safe(denom)[..., None]
    best_d = torch.where(inside, dot(p - (best_b[..., :1] * a + best_b[..., 1:2] * b + best_b[..., 2:] * c),
                                     p - (best_b[..., :1] * a + best_b[..., 1:2] * b + best_b[..., 2:] * c)),
                         torch.full_like(d1, float("inf")))
    bc = c - b
    edges = (  # (start, direction, param -> barycentrics)
        (a, ab, ap, lambda t: torch.stack([1 - t, t, z], -1)),
        (a, ac, ap, lambda t: torch.stack([1 - t, z, t], -1)),
        (b, bc, bp, lambda t: torch.stack([z, 1 - t, t], -1)),
    )
    for start, e, rel, to_bary in edges:
        t = (dot(rel, e) / safe(dot(e, e))).clamp(0, 1)
        q = start + t[..., None] * e
        d = dot(p - q, p - q)
        better = d < best_d
        best_d = torch.where(better, d, best_d)
        best_b = torch.where(better[..., None], to_bary(t), best_b)
    return best_b


def point_mesh_distance(points: torch.Tensor, mesh: Mesh, chunk: int = 1 << 21
                        ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact unsigned distance from each point to the mesh surface (brute force over
    faces, chunked to ``chunk`` point-face pairs at a time).

    Args:
        points: (P, 3) world points.
        mesh: triangle mesh with F >= 1 faces.
    Returns:
        distance (P,), face (P,) long index of the closest face, bary (P, 3) barycentrics
        of the closest point on that face (w.r.t. ``mesh.faces[face]``).
    """
    if mesh.num_faces == 0:
        raise UserError("point_mesh_distance needs a mesh with at least one face")
    fv = mesh.face_verts().to(points.dtype)  # (F, 3, 3)
    a, b, c = fv[:, 0], fv[:, 1], fv[:, 2]
    step = max(1, chunk // mesh.num_faces)
    dists, faces = [], []
    for s in range(0, points.shape[0], step):
        p = points[s:s + step, None, :]  # (n, 1, 3)
        bary = _closest_on_triangles(p, a, b, c)  # (n, F, 3)
        q = bary[..., :1] * a + bary[..., 1:2] * b + bary[..., 2:] * c
        d2, f = (q - p).square().sum(-1).min(dim=1)
        dists.append(d2.sqrt())
        faces.append(f)
    dist = torch.cat(dists) if dists else points.new_zeros(0)
    face = torch.cat(faces) if faces else torch.zeros(0, dtype=torch.long, device=points.device)
    bary = _closest_on_triangles(points, a[face], b[face], c[face])
    return dist, face, bary
