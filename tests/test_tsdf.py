"""TSDF fusion of analytic depth maps (a sphere, a plane seen from above) and its mesh: within a
voxel of the truth, the colours fused, a surface seen by one view only carved by the others,
and the normals of a depth map."""

from __future__ import annotations

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.depth_normals import depth_to_normals
from l3d_app.geometry.rays import camera_rays
from l3d_app.geometry.tsdf import fuse_depth_maps, tsdf_mesh

R_SPHERE = 0.6


def _sphere_depth(cams, centre=(0.0, 0.0, 0.0), radius=R_SPHERE):
    """Camera z of the first ray-sphere hit per pixel (0 = miss), and a colour by the hit's x sign."""
    o, d = camera_rays(cams, normalize=False)                 # camera z = 1: the ray parameter is the depth
    c = torch.tensor(centre)
    oc = o - c
    a, b, cc = (d * d).sum(-1), 2 * (oc * d).sum(-1), (oc * oc).sum(-1) - radius ** 2
    disc = b * b - 4 * a * cc
    t = (-b - torch.sqrt(disc.clamp_min(0))) / (2 * a)
    hit = disc > 0
    depth = torch.where(hit, t, torch.zeros_like(t))
    x = (o + depth[..., None] * d)[..., 0]
    rgb = torch.stack([(x > 0).float(), torch.zeros_like(x), (x <= 0).float()], -1)
    return depth, hit, rgb


def _views(n=10, size=64):
    elev = torch.tensor([60.0, 30.0, 0.0, -30.0, -60.0] * (n // 5))
    azim = torch.linspace(0, 360, n + 1)[:-1]
    return look_at_cameras(2.5, elev, azim, 50.0, size)


def test_a_sphere_fused_from_ten_views_lies_within_a_voxel_of_the_truth_and_keeps_its_colours():
    cams = _views(10, 128)                     # a pixel at the sphere: about a voxel
    depth, hit, rgb = _sphere_depth(cams)
    voxel = 0.02
    vol = fuse_depth_maps(depth, cams, voxel, 4 * voxel, colors=rgb, valid=hit)
    mesh = tsdf_mesh(vol)
    r = mesh.verts.norm(dim=-1)
    assert float((r - R_SPHERE).abs().max()) < voxel
    # the whole sphere is there: every point of a fine sampling has a vertex within two voxels
    g = torch.Generator().manual_seed(0)
    s = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1) * R_SPHERE
    assert float(torch.cdist(s, mesh.verts).min(1).values.max()) < 2 * voxel
    # colours fused: red where x > 0, blue where x < 0 (away from the seam)
    far = mesh.verts[:, 0].abs() > 3 * voxel
    want = torch.stack([(mesh.verts[:, 0] > 0).float(), torch.zeros(len(r)), (mesh.verts[:, 0] <= 0).float()], -1)
    assert float((mesh.vert_colors[far] - want[far]).abs().max()) < 0.05
    # outward faces: the signed volume of a closed surface around the origin is positive
    v = mesh.face_verts()
    vol6 = (v[:, 0] * torch.cross(v[:, 1], v[:, 2], dim=-1)).sum()
    assert float(vol6) / 6 == pytest.approx(4 / 3 * torch.pi * R_SPHERE ** 3, rel=0.05)


def test_a_plane_seen_from_above_is_fused_flat_and_open_where_nothing_measured():
    elev = torch.tensor([80.0, 60.0, 45.0, 70.0, 50.0])
    azim = torch.tensor([0.0, 70.0, 150.0, 220.0, 300.0])
    cams = look_at_cameras(2.0, elev, azim, 60.0, 96)
    o, d = camera_rays(cams, normalize=False)
    y0 = 0.004                                                  # the plane y = y0 (off the grid's layers)
    depth = (y0 - o[..., 1]) / d[..., 1]
    p = o + depth[..., None] * d
    valid = (p[..., 0].abs() < 0.7) & (p[..., 2].abs() < 0.7)  # a square of it
    voxel = 0.015
    mesh = tsdf_mesh(fuse_depth_maps(depth, cams, voxel, 5 * voxel, valid=valid, carve=False))
    assert float((mesh.verts[:, 1] - y0).abs().max()) < voxel
    assert float(mesh.verts[:, [0, 2]].abs().max()) < 0.7 + 2 * voxel     # ends where the measurements do
    n, a = mesh.face_normals(), mesh.face_areas()
    centre = mesh.face_verts().mean(1)
    inner = (centre[:, [0, 2]].abs() < 0.7 - 5 * voxel).all(-1) & (a > 1e-10)  # off the open edge, not degenerate
    assert float(n[inner, 1].min()) > 0.999                          # facing up, towards the cameras
    assert float(n[a > 1e-10, 1].min()) > 0.0                        # (tilted only along the open edge)
    area = float(a.sum())
    assert area == pytest.approx(1.4 * 1.4, rel=0.05)


def test_a_floater_seen_by_one_view_is_carved_by_the_others():
    cams = _views()
    depth, hit, _ = _sphere_depth(cams)
    fd, fh, _ = _sphere_depth(cams[:1], centre=(0.0, 1.2, 0.0), radius=0.15)     # only view 0 shows it
    d0 = torch.where(fh[0] & ((fd[0] < depth[0]) | ~hit[0]), fd[0], depth[0])
    depth, hit = torch.cat([d0[None], depth[1:]]), torch.cat([(hit[0] | fh[0])[None], hit[1:]])
    voxel = 0.03
    kept = tsdf_mesh(fuse_depth_maps(depth, cams, voxel, 4 * voxel, valid=hit, carve=False))
    carved = tsdf_mesh(fuse_depth_maps(depth, cams, voxel, 4 * voxel, valid=hit, carve=True))
    near_floater = lambda m: int(((m.verts - torch.tensor([0.0, 1.2, 0.0])).norm(dim=-1) < 0.3).sum())  # noqa: E731
    assert near_floater(kept) > 20 and near_floater(carved) == 0
    assert float((carved.verts.norm(dim=-1) - R_SPHERE).abs().max()) < voxel


def test_fusion_refuses_bad_sizes_and_empty_input():
    cams = _views()
    depth, hit, _ = _sphere_depth(cams)
    with pytest.raises(UserError):
        fuse_depth_maps(depth, cams, 0.02, 0.01)
    with pytest.raises(UserError):
        fuse_depth_maps(depth, cams, 0.02, 0.08, valid=torch.zeros_like(hit))


def test_depth_normals_of_a_sphere_are_its_radial_normals_facing_the_camera():
    cams = _views(5, 48)
    depth, hit, _ = _sphere_depth(cams)
    n = depth_to_normals(depth, cams)
    o, d = camera_rays(cams, normalize=False)
    p = o + depth[..., None] * d
    inner = hit.clone()
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        inner &= torch.roll(hit, (dy, dx), (1, 2))
    inner[:, [0, -1]] = False
    inner[:, :, [0, -1]] = False
    cos = (n * torch.nn.functional.normalize(p, dim=-1)).sum(-1)[inner]
    assert float(cos.min()) > 0.98
    depth.requires_grad_(True)
    depth_to_normals(depth, cams)[inner].sum().backward()
    assert bool(torch.isfinite(depth.grad).all())
