"""RGB-D views and true depth maps of a mesh, rendered by our rasteriser (the inverse,
depth -> points, is :func:`l3d_app.geometry.rgbd.unproject_depth`)."""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.render.mesh.renderer import MeshRenderer, scale_cameras


def rgbd_from_mesh(mesh: Mesh, cams: Cameras, renderer=None) -> Dict[str, torch.Tensor]:
    """Render RGB-D views of a mesh: rgb (B, H, W, 3) albedo, depth (B, H, W) camera Z
    (0 on background), mask (B, H, W) bool. ``renderer`` defaults to an unlit
    ``MeshRenderer`` (colours = albedo); supersampling is refused (it blurs depth)."""
    renderer = renderer or MeshRenderer(shading="unlit")
    if getattr(renderer, "antialias", 1) != 1:
        raise UserError("rgbd_from_mesh needs antialias=1: averaged depths lie off the surface")
    out = renderer(mesh, cams)
    mask = out["alpha"] > 0.5
    return {"rgb": out["image"], "depth": torch.where(mask, out["depth"], 0.0), "mask": mask}


@torch.no_grad()
def true_depth_maps(mesh: Mesh, cameras: Cameras, scale: int = 4, batch: int = 8) -> torch.Tensor:
    """(B, scale*H, scale*W) camera-Z depth (world units) of ``mesh`` seen by ``cameras``,
    +inf where no face covers the pixel centre."""
    if int(scale) < 1:
        raise UserError(f"observed: scale must be an integer >= 1, got {scale}")
    cams = scale_cameras(cameras, int(scale)) if int(scale) > 1 else cameras
    renderer = MeshRenderer(shading="unlit", antialias=1)
    maps = []
    for s in range(0, len(cams), int(batch)):
        out = renderer(mesh, cams[s:s + int(batch)])
        depth = torch.where(out["alpha"] > 0, out["depth"], torch.full_like(out["depth"], float("inf")))
        maps.append(depth)
    return torch.cat(maps)
