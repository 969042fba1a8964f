"""RGB-D unprojection, mesh -> RGB-D -> points round trip, point-to-mesh distance."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from l3d_app.data.rgbd_views import rgbd_views
from l3d_app.data.scenes import builtin_scene
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, look_at, look_at_cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.point_mesh_distance import point_mesh_distance
from l3d_app.geometry.rgbd import unproject_depth, unproject_views
from l3d_app.registry import DATASETS
from l3d_app.render.mesh.renderer import MeshRenderer
from l3d_app.render.mesh.rgbd import rgbd_from_mesh

REPO = Path(__file__).resolve().parents[1]


def ring_cams(n=3, size=40, dist=3.0, elev=20.0, dtype=torch.float32):
    R, t = look_at(dist, elev, [360.0 * k / n + 10.0 for k in range(n)], dtype=dtype)
    return Cameras.from_fov(R, t, 50.0, size, size)


# ------------------------------------------------------------- point_mesh_distance
def test_point_triangle_distance_known_regions():
    tri = Mesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64),
               torch.tensor([[0, 1, 2]]))
    pts = torch.tensor([[0.2, 0.2, 0.5],    # above interior
                        [-1.0, -1.0, 0.0],  # beyond vertex a
                        [2.0, -0.5, 0.0],   # beyond vertex b
                        [0.5, -2.0, 1.0],   # beyond edge ab
                        [1.0, 1.0, 0.0],    # beyond edge bc
                        [-3.0, 0.5, 0.0],   # beyond edge ca
                        [0.0, 3.0, -1.0]],  # beyond vertex c
                       dtype=torch.float64)
    expect = torch.tensor([0.5, 2 ** 0.5, (1 + 0.25) ** 0.5, (4 + 1) ** 0.5, 0.5 ** 0.5, 3.0,
                           (4 + 1) ** 0.5], dtype=torch.float64)
    d, f, bary = point_mesh_distance(pts, tri)
    torch.testing.assert_close(d, expect)
    assert torch.all(f == 0)
    torch.testing.assert_close(bary[0], torch.tensor([0.6, 0.2, 0.2], dtype=torch.float64))
    torch.testing.assert_close(bary.sum(-1), torch.ones(7, dtype=torch.float64))


def test_point_mesh_distance_mixed_face_sizes_is_exact_and_stays_local(monkeypatch):
    """A finely tessellated plate (5000 small triangles) and two large triangles above it:
    distances equal a brute-force float64 minimum over every face, and the candidate pairs
    stay local (one global max face radius listed about every plate face per point)."""
    import l3d_app.geometry.point_mesh_distance as pmd

    n = 50                                            # 50 x 50 cells, 2 triangles each, on z = 0
    u = torch.linspace(-1.0, 1.0, n + 1, dtype=torch.float64)
    gx, gy = torch.meshgrid(u, u, indexing="ij")
    verts = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.zeros((n + 1) ** 2, dtype=torch.float64)], 1)
    k = (torch.arange(n)[:, None] * (n + 1) + torch.arange(n)[None, :]).reshape(-1)
    faces = torch.cat([torch.stack([k, k + n + 1, k + 1], 1), torch.stack([k + 1, k + n + 1, k + n + 2], 1)])
    big = torch.tensor([[-0.9, -0.9, 0.3], [0.9, -0.9, 0.3], [0.0, 0.9, 0.3], [0.0, 0.0, 0.8]], dtype=torch.float64)
    big_faces = torch.tensor([[0, 1, 2], [0, 1, 3]]) + verts.shape[0]
    mesh = Mesh(torch.cat([verts, big]), torch.cat([faces, big_faces]))
    g = torch.Generator().manual_seed(3)
    pts = (torch.rand(400, 3, generator=g, dtype=torch.float64) * 2.4 - 1.2) * torch.tensor([1.0, 1.0, 0.5],
                                                                                            dtype=torch.float64)
    listed = []
    real = pmd._candidates
    monkeypatch.setattr(pmd, "_candidates", lambda *a: listed.append(real(*a)[0].numel()) or real(*a))
    d, f, _ = point_mesh_distance(pts, mesh)
    tri = mesh.verts[mesh.faces]
    brute = pmd.point_triangle_distance(pts[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])  # (400, F)
    torch.testing.assert_close(d, brute.min(1).values, rtol=0, atol=1e-12)
    torch.testing.assert_close(brute[torch.arange(400), f], d, rtol=0, atol=1e-12)
    # candidates listed before the exact test: 48 per point here; with one global max radius 3443
    assert sum(listed) < 200 * pts.shape[0], sum(listed)


def test_point_mesh_distance_matches_dense_sampling():
    g = torch.Generator().manual_seed(0)
    verts = torch.randn(6, 3, generator=g, dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [2, 3, 4], [1, 4, 5], [0, 0, 3]])  # last one degenerate
    mesh = Mesh(verts, faces)
    pts = torch.randn(50, 3, generator=g, dtype=torch.float64) * 1.5
    d, f, bary = point_mesh_distance(pts, mesh)
    # dense barycentric grid on every face: an upper bound that converges to the truth
    n = 120
    i, j = torch.meshgrid(torch.arange(n + 1), torch.arange(n + 1), indexing="ij")
    keep = i + j <= n
    b = torch.stack([i[keep], j[keep], n - i[keep] - j[keep]], -1).double() / n
    samples = torch.einsum("sk,fkd->fsd", b, verts[faces]).reshape(-1, 3)
    d_dense = torch.cdist(pts, samples).min(dim=1).values
    assert torch.all(d <= d_dense + 1e-12)
    assert torch.all(d_dense - d < 0.01)
    q = torch.einsum("pk,pkd->pd", bary, verts[faces[f]])
    torch.testing.assert_close((q - pts).norm(dim=-1), d)
    assert torch.isfinite(d).all() and torch.isfinite(bary).all()


# ------------------------------------------------------------------ unproject_depth
def test_unproject_drops_invalid_and_masked_pixels_and_reprojects():
    cams = ring_cams(2, size=12, dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    H, W = 12, 12
    depth = 1.0 + torch.rand(2, H, W, generator=g, dtype=torch.float64) * 3
    depth[0, 0, :5] = 0.0
    depth[0, 1, 0] = -2.0
    depth[1, 2, 3] = float("nan")
    depth[1, 4, 4] = float("inf")
    mask = torch.ones(2, H, W, dtype=torch.bool)
    mask[1, 5:, :] = False
    rgb = torch.rand(2, H, W, 3, generator=g, dtype=torch.float64)
    cloud = unproject_depth(depth, cams, rgb, mask)
    valid = torch.isfinite(depth) & (depth > 0) & mask
    assert cloud.num_points == int(valid.sum()) == 2 * H * W - 5 - 1 - 2 - 7 * W
    torch.testing.assert_close(cloud.colors, rgb[valid])
    # each point projects back onto its pixel centre with its depth
    view_of = torch.arange(2)[:, None, None].expand(2, H, W)[valid]
    rows, cols = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    for b in range(2):
        uv, z = cams[b].project(cloud.points[view_of == b])
        sel = valid[b]
        torch.testing.assert_close(z[0], depth[b][sel])
        torch.testing.assert_close(uv[0, :, 0], cols[sel].double() + 0.5)
        torch.testing.assert_close(uv[0, :, 1], rows[sel].double() + 0.5)


def test_unproject_views_list_and_errors():
    c1, c2 = ring_cams(2, size=8), ring_cams(1, size=6)
    d1, d2 = torch.full((2, 8, 8), 2.0), torch.full((1, 6, 6), 3.0)
    cloud = unproject_views([d1, d2], [c1, c2])
    assert cloud.num_points == 2 * 64 + 36 and cloud.colors is None
    with pytest.raises(UserError):
        unproject_depth(d1, c2)
    with pytest.raises(UserError):
        unproject_views([d1, d2], c1)


# ------------------------------------------------------------ round trip via a mesh
@pytest.mark.parametrize("scene", ["orientation", "torus"])
def test_mesh_rgbd_round_trip_points_on_surface(scene):
    mesh = builtin_scene(scene)
    cams = ring_cams(3, size=36)
    views = rgbd_from_mesh(mesh, cams)
    assert views["mask"].sum() > 300
    assert torch.all(views["depth"][~views["mask"]] == 0)
    cloud = unproject_depth(views["depth"], cams, views["rgb"], views["mask"])
    assert cloud.num_points == int(views["mask"].sum())
    lo, hi = mesh.bounds()
    size = (hi - lo).norm().item()
    d, f, bary = point_mesh_distance(cloud.points.double(), mesh.to(dtype=torch.float64))
    assert d.max().item() < 1e-3 * size
    if scene == "torus":  # smooth vertex colours: albedo at the closest point
        albedo = torch.einsum("pk,pkc->pc", bary, mesh.vert_colors.double()[mesh.faces[f]])
        torch.testing.assert_close(cloud.colors.double(), albedo, atol=2e-3, rtol=0)
    else:  # piecewise-constant part colours: nearly every point has its part's colour
        albedo = torch.einsum("pk,pkc->pc", bary, mesh.vert_colors.double()[mesh.faces[f]])
        close = (cloud.colors.double() - albedo).abs().max(-1).values < 1e-3
        assert close.float().mean() > 0.99


def test_rgbd_from_mesh_refuses_supersampling():
    with pytest.raises(UserError):
        rgbd_from_mesh(builtin_scene("cube"), ring_cams(1, 8), MeshRenderer(shading="unlit", antialias=2))


def test_rgbd_views_union_has_every_view_in_one_frame():
    n, size = 4, 32
    cloud = rgbd_views("orientation", num_views=n, image_size=size)
    mesh = builtin_scene("orientation")
    cams = look_at_cameras(3.0, 20.0, [90.0 * k for k in range(n)], 50.0, size)
    counts = [int(rgbd_from_mesh(mesh, cams[k])["mask"].sum()) for k in range(n)]
    assert cloud.num_points == sum(counts) and min(counts) > 100
    start = 0
    for k in range(n):  # view k's block reprojects inside view k with the right depth
        block = cloud.points[start:start + counts[k]]
        start += counts[k]
        _, z = cams[k].project(block)
        assert torch.all(z > 0)
        # and lies on the side of the scene facing camera k
        facing = (block @ cams[k].R[0, 2])  # coordinate along camera k's viewing direction
        assert facing.mean() < 0.1
    d, _, _ = point_mesh_distance(cloud.points.double(), mesh.to(dtype=torch.float64))
    assert d.max() < 5e-3


def test_rgbd_data_source_config():
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(REPO / "conf" / "data" / "rgbd.yaml")
    assert cfg.name == "rgbd"
    cfg.image_size, cfg.num_views = 24, 2
    cloud = DATASETS.build(cfg)
    assert cloud.num_points > 50 and cloud.colors is not None
    with pytest.raises(UserError):
        rgbd_views(num_views=0)
