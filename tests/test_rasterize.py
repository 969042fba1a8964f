"""Hard rasteriser vs a naive float64 per-pixel reference; shading on analytic cases."""

import math

import pytest
import torch

from l3d_app.geometry.cameras import Cameras, look_at
from l3d_app.geometry.mesh import Mesh
from l3d_app.registry import RENDERERS
from l3d_app.render.mesh.renderer import DEFAULT_ALBEDO, MeshRenderer
from l3d_app.render.mesh.rasterize import rasterize
from l3d_app.render.mesh.shading import Lights, Material, interpolate, lambert, phong
from l3d_app.geometry.textures import sample_texture

TIE_PX = 1e-4  # pixel centres this close to a triangle edge are ties (excluded)


# ----------------------------------------------------------------- reference
def naive_rasterize(cams: Cameras, verts: torch.Tensor, faces: torch.Tensor, near: float = 1e-3):
    """Every pixel x every face in float64: (p2f, zbuf, bary, ambiguous), each (B, H, W, ...).

    ``ambiguous`` marks pixel centres within TIE_PX of an edge of a candidate face, or
    where the two nearest faces are at (nearly) equal depth.
    """
    c = cams.to(dtype=torch.float64)
    view = c.world_to_view(verts.double())                          # (B, V, 3)
    z = view[..., 2]
    uv = view[..., :2] / z[..., None].clamp_min(near) * torch.stack([c.fx, c.fy], -1)[:, None] \
        + torch.stack([c.cx, c.cy], -1)[:, None]
    H, W = cams.height, cams.width
    jj, ii = torch.meshgrid(torch.arange(W, dtype=torch.float64) + 0.5,
                            torch.arange(H, dtype=torch.float64) + 0.5, indexing="xy")
    p = torch.stack([jj, ii], -1).reshape(-1, 2)                    # (HW, 2) (u, v)
    fuv, fz = uv[:, faces], z[:, faces]                             # (B, F, 3, 2), (B, F, 3)
    a, b = fuv[:, :, [1, 2, 0]], fuv[:, :, [2, 0, 1]]               # edge k opposite vertex k
    d = b - a
    rel = p[:, None, None, None, :] - a[None]                       # (HW, B, F, 3, 2)
    E = d[..., 0] * rel[..., 1] - d[..., 1] * rel[..., 0]           # (HW, B, F, 3)
    area2 = E.sum(-1)
    sign = torch.sign(area2)[..., None]
    dist = E * sign / d.norm(dim=-1).clamp_min(1e-300)              # signed distance to edges
    valid = (fz >= near).all(-1)[None] & (area2.abs() > 1e-9)
    inside = valid & (dist >= 0).all(-1)
    near_edge = valid & (dist.min(-1).values.abs() < TIE_PX)
    wE = E / fz[None]
    depth = area2 / wE.sum(-1)
    depth = torch.where(inside, depth, torch.inf)
    best = depth.topk(2, dim=-1, largest=False)
    p2f = torch.where(best.values[..., 0].isfinite(), best.indices[..., 0], -1)
    zbuf = torch.where(p2f >= 0, best.values[..., 0], 0.0)
    bary = wE / wE.sum(-1, keepdim=True)
    bary = torch.gather(bary, 2, p2f.clamp_min(0)[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]
    bary = torch.where(p2f[..., None] >= 0, bary, 0.0)
    z_tie = (best.values[..., 1] - best.values[..., 0]).abs() < 1e-5 * best.values[..., 0].abs()
    ambiguous = near_edge.any(-1) | (z_tie & best.values[..., 0].isfinite())
    shape = lambda x: x.reshape(H, W, *x.shape[1:]).movedim(2, 0)  # noqa: E731
    return shape(p2f), shape(zbuf), shape(bary), shape(ambiguous)


def random_scene(seed: int, n_verts=18, n_faces=24, size=(37, 29), batch=2):
    g = torch.Generator().manual_seed(seed)
    verts = torch.rand(n_verts, 3, generator=g) * 2 - 1
    faces = torch.stack([torch.randperm(n_verts, generator=g)[:3] for _ in range(n_faces)])
    elev = torch.rand(batch, generator=g) * 120 - 60
    azim = torch.rand(batch, generator=g) * 360
    R, t = look_at(3.0, elev, azim)
    return verts, faces, Cameras.from_fov(R, t, 55.0, size[0], size[1])


def assert_matches_reference(cams, verts, faces, near=1e-3, min_checked=0.9, **kw):
    frags = rasterize(cams, verts, faces, near=near, **kw)
    p2f, zbuf, bary, amb = naive_rasterize(cams, verts, faces, near)
    for x in (frags.bary, frags.zbuf, frags.bary_screen):
        assert torch.isfinite(x).all()
    ok = ~amb
    assert ok.float().mean() > min_checked  # the comparison is not vacuous
    assert torch.equal(frags.pix_to_face[ok], p2f[ok])
    torch.testing.assert_close(frags.zbuf[ok].double(), zbuf[ok], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(frags.bary[ok].double(), bary[ok], rtol=0, atol=2e-4)
    return frags


# ----------------------------------------------------------------- rasteriser
@pytest.mark.parametrize("seed", range(5))
def test_matches_naive_reference(seed):
    verts, faces, cams = random_scene(seed)
    frags = assert_matches_reference(cams, verts, faces)
    assert frags.mask.any() and (~frags.mask).any()
    covered = frags.mask
    torch.testing.assert_close(frags.bary[covered].sum(-1), torch.ones(int(covered.sum())))
    assert (frags.bary[covered] >= 0).all() and (frags.bary_screen[covered] >= 0).all()
    assert (frags.zbuf[~covered] == 0).all() and (frags.bary[~covered] == 0).all()


def test_chunking_and_batched_verts_give_identical_results():
    verts, faces, cams = random_scene(7)
    ref = rasterize(cams, verts, faces)
    small = rasterize(cams, verts, faces, max_candidates=13)
    batched = rasterize(cams, verts[None].expand(2, -1, -1).contiguous(), faces)
    for other in (small, batched):
        assert torch.equal(ref.pix_to_face, other.pix_to_face)
        assert torch.equal(ref.bary, other.bary) and torch.equal(ref.zbuf, other.zbuf)


def test_float64_inputs_match_reference():
    verts, faces, cams = random_scene(11)
    assert_matches_reference(cams.to(dtype=torch.float64), verts.double(), faces)


def test_shared_edge_has_no_cracks():
    """A grid of quads whose diagonals run exactly through pixel centres."""
    n = 8
    ys, xs = torch.meshgrid(torch.arange(n + 1.0), torch.arange(n + 1.0), indexing="ij")
    verts = torch.stack([xs, ys, torch.full_like(xs, 4.0)], -1).reshape(-1, 3)
    idx = torch.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = torch.cat([torch.stack([a, b, c], -1), torch.stack([a, c, d], -1)]).reshape(-1, 3)
    # camera: identity pose, 4 px per world unit at depth 4, so grid corners hit pixel
    # centres and every diagonal passes exactly through pixel centres
    cams = Cameras(torch.eye(3), torch.zeros(3), 16.0, 16.0, 0.5, 0.5, 4 * n, 4 * n)
    frags = rasterize(cams, verts, faces)
    inner = frags.mask[0, : 4 * n - 3, : 4 * n - 3]
    assert inner.all(), "pixel centres on shared edges were dropped"


def test_huge_triangles_and_equal_depth_ties():
    """Triangles spanning far beyond the image (tiles clamped to it); coincident faces."""
    cams = Cameras(torch.eye(3), torch.zeros(3), 20.0, 20.0, 15.0, 11.0, 30, 22)
    verts = torch.tensor([[-300.0, -200.0, 5.0], [400.0, -150.0, 6.0], [0.0, 500.0, 4.0],
                          [-1.0, -1.0, 3.0], [1.0, -1.0, 3.0], [0.0, 1.0, 3.0]])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [3, 4, 5]])  # faces 1 and 2 coincide
    frags = assert_matches_reference(cams, verts, faces, min_checked=0.6)
    assert frags.mask.all()
    small = frags.pix_to_face[frags.pix_to_face != 0]
    assert small.numel() > 10 and (small == 1).all()  # equal depths: lowest face id wins


def test_degenerate_triangles_cover_nothing():
    verts = torch.tensor([[-0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [0.0, 0.0, 0.0],
                          [0.3, -0.2, 0.0], [0.3, -0.2, 0.0]])
    faces = torch.tensor([[0, 1, 2], [0, 3, 4], [3, 3, 3], [0, 2, 1]])
    R, t = look_at(2.0, 10.0, 20.0)
    cams = Cameras.from_fov(R, t, 60.0, 32, 32)
    frags = rasterize(cams, verts, faces)
    assert not frags.mask.any()
    assert torch.isfinite(frags.zbuf).all() and torch.isfinite(frags.bary).all()
    # collinear triples on lines through pixel centres (rounding makes them near-zero area)
    g = torch.Generator().manual_seed(0)
    start = torch.randint(0, 8, (200, 1, 2), generator=g).float()
    step = torch.randint(-3, 4, (200, 1, 2), generator=g).float()
    xy = (start + torch.rand(200, 3, 1, generator=g) * 3 * step).reshape(-1, 2)
    verts = torch.cat([xy, torch.full((600, 1), 4.0)], 1)
    cams = Cameras(torch.eye(3), torch.zeros(3), 16.0, 16.0, 0.5, 0.5, 32, 32)  # u = 4x + .5
    frags = rasterize(cams, verts, torch.arange(600).reshape(200, 3))
    assert not frags.mask.any()


def test_triangle_crossing_near_plane_is_dropped_whole():
    cams = Cameras(torch.eye(3), torch.zeros(3), 20.0, 20.0, 16.0, 16.0, 32, 32)
    verts = torch.tensor([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, -1.0],  # crosses Z=0
                          [-1.0, 0.5, 3.0], [1.0, 0.5, 3.0], [0.0, 1.5, 3.0],     # in front
                          [0.0, 0.0, 0.0]])                                        # at the centre
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [0, 1, 6]])
    frags = rasterize(cams, verts, faces, near=0.1)
    assert torch.isfinite(frags.zbuf).all() and torch.isfinite(frags.bary).all()
    assert set(frags.pix_to_face.unique().tolist()) == {-1, 1}
    assert_matches_reference(cams, verts, faces, near=0.1)


@pytest.mark.parametrize("where", ["outside", "behind"])
def test_mesh_out_of_view_is_background(where):
    verts, faces, _ = random_scene(3)
    cams = Cameras(torch.eye(3), torch.zeros(3), 30.0, 30.0, 16.0, 16.0, 32, 32)
    shift = torch.tensor([40.0, 0.0, 5.0]) if where == "outside" else torch.tensor([0.0, 0.0, -5.0])
    frags = rasterize(cams, verts + shift, faces)
    assert not frags.mask.any() and (frags.zbuf == 0).all()


def test_backface_culling_keeps_front_faces():
    mesh = _quad()
    cams = _front_camera()
    front = rasterize(cams, mesh.verts, mesh.faces, cull_backfaces=True)
    back = rasterize(cams, mesh.verts, mesh.faces.flip(-1), cull_backfaces=True)
    both = rasterize(cams, mesh.verts, mesh.faces.flip(-1))
    assert front.mask.sum() > 100 and not back.mask.any() and torch.equal(both.mask, front.mask)


def test_gradients_reach_vertices_and_are_finite():
    verts, faces, cams = random_scene(5)
    verts = verts.clone().requires_grad_(True)
    frags = rasterize(cams, verts, faces)
    (frags.zbuf.sum() + (frags.bary * torch.arange(3.0)).sum()).backward()
    assert torch.isfinite(verts.grad).all() and verts.grad.abs().sum() > 0


# ----------------------------------------------------------------- shading
def _quad(**appearance) -> Mesh:
    """Unit quad [-1, 1]^2 in the z = 0 plane, counter-clockwise seen from +z."""
    verts = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return Mesh(verts, faces, **appearance)


def _front_camera(size=32) -> Cameras:
    R, t = look_at(3.0, 0.0, 0.0)  # at (0, 0, 3), looking down -z, world +y up in the image
    return Cameras.from_fov(R, t, 50.0, size, size)


@pytest.mark.parametrize("light_direction", [(0.0, 0.0, 1.0), None])  # None = headlight
def test_lambert_quad_facing_light_is_exact(light_direction):
    albedo = torch.tensor([0.2, 0.5, 0.9])
    mesh = _quad(vert_colors=albedo.expand(4, 3).clone())
    r = MeshRenderer(shading="lambert", ambient=0.3, diffuse=0.6, light_direction=light_direction,
                     background=(0, 0, 0))
    out = r(mesh, _front_camera())
    m = out["alpha"] > 0
    assert m.sum() > 100
    torch.testing.assert_close(out["image"][m], (albedo * 0.9).expand(int(m.sum()), 3))
    torch.testing.assert_close(out["normals"][m], torch.tensor([0.0, 0, 1]).expand(int(m.sum()), 3))
    torch.testing.assert_close(out["depth"][m], torch.full((int(m.sum()),), 3.0))
    assert (out["image"][~m] == 0).all()


def test_phong_and_lambert_analytic():
    """Channel-first (3, P) inputs, P = 1."""
    n = torch.tensor([[0.0], [0.0], [1.0]])
    p0 = torch.zeros(3, 1)
    albedo = torch.tensor([[0.5], [0.5], [0.5]])
    mat = Material(ambient=0.1, diffuse=0.7, specular=0.4, shininess=8.0)
    tilt = (math.sin(math.pi / 3), 0.0, math.cos(math.pi / 3))  # 60 degrees off the normal
    lights = Lights(ambient=1.0, directional=[(tilt, (1.0, 1.0, 1.0))])
    torch.testing.assert_close(lambert(p0, n, albedo, lights, mat), albedo * (0.1 + 0.7 * 0.5))
    # light and eye on the normal: mirror direction = view direction, specular = ks
    head = Lights(ambient=1.0, directional=[((0.0, 0.0, 2.0), (1.0, 1.0, 1.0))])
    ph = phong(p0, n, albedo, torch.tensor([0.0, 0.0, 5.0]), head, mat)
    torch.testing.assert_close(ph, albedo * 0.8 + 0.4)
    # point light straight above the point, eye at 60 degrees: (r.v)^8 = 0.5^8
    pt = Lights(ambient=0.0, point=[((0.0, 0.0, 3.0), (1.0, 1.0, 1.0))])
    ph = phong(p0, n, albedo, torch.tensor(tilt), pt, mat)
    torch.testing.assert_close(ph, albedo * 0.7 + 0.4 * 0.5 ** 8)
    # coloured light and material: products per channel
    coloured = Lights(ambient=(0.0, 0.0, 0.0), directional=[((0.0, 0.0, 1.0), (1.0, 0.5, 0.0))])
    ph = phong(p0, n, albedo, torch.tensor([0.0, 0.0, 5.0]), coloured,
               Material(0.0, (1.0, 1.0, 0.5), (0.0, 1.0, 1.0), 8.0))
    torch.testing.assert_close(ph, torch.tensor([[0.5], [0.25 + 0.5], [0.0]]))
    # light from behind: neither diffuse nor specular
    back = Lights(ambient=0.0, directional=[((0.0, 0.0, -1.0), (1.0, 1.0, 1.0))])
    assert phong(p0, n, albedo, torch.tensor([0.0, 0.0, 5.0]), back, mat).abs().max() == 0


def test_texture_orientation_v_up_and_faces_uvs():
    # 2x2 texture, top row first: top-left red, top-right green, bottom-left blue,
    # bottom-right white
    tex = torch.tensor([[[1.0, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 1, 1]]])
    # texel centres in (u, v-up) coordinates
    uv = torch.tensor([[0.25, 0.75], [0.75, 0.75], [0.25, 0.25], [0.75, 0.25]])
    torch.testing.assert_close(sample_texture(tex, uv), tex.reshape(4, 3))
    # quad corners (bottom-left, bottom-right, top-right, top-left) get uvs stored shuffled
    verts_uvs = torch.tensor([[1.0, 1.0], [0.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    faces_uvs = torch.tensor([[1, 3, 0], [1, 0, 2]])
    mesh = _quad(verts_uvs=verts_uvs, faces_uvs=faces_uvs, texture=tex)
    img = MeshRenderer(shading="unlit")(mesh, _front_camera(64))["image"][0]
    corners = {(14, 14): [1.0, 0, 0], (14, 49): [0, 1.0, 0],    # (row, column): colour
               (49, 14): [0, 0, 1.0], (49, 49): [1.0, 1, 1]}
    for (i, j), colour in corners.items():
        torch.testing.assert_close(img[i, j], torch.tensor(colour))


def test_vertex_colour_at_a_vertex_is_that_colour():
    colors = torch.tensor([[0.9, 0.1, 0.2], [0.1, 0.8, 0.3], [0.2, 0.3, 0.7]])
    mesh = Mesh(torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
                torch.tensor([[0, 1, 2]]), vert_colors=colors)
    # identity pose at distance 3: world origin projects exactly onto pixel (10, 10)'s centre
    cams = Cameras(torch.eye(3), torch.tensor([0.0, 0.0, 3.0]), 30.0, 30.0, 10.5, 10.5, 32, 32)
    frags = rasterize(cams, mesh.verts, mesh.faces)
    assert frags.pix_to_face[0, 10, 10] == 0
    torch.testing.assert_close(frags.bary[0, 10, 10], torch.tensor([1.0, 0, 0]))
    img = MeshRenderer(shading="unlit")(mesh, cams)["image"]
    torch.testing.assert_close(img[0, 10, 10], colors[0])
    dense = interpolate(frags, colors[mesh.faces])
    torch.testing.assert_close(dense[0, 10, 10], colors[0])
    torch.testing.assert_close(dense[frags.mask], img[frags.mask])


@pytest.mark.parametrize("shading", ["phong", "lambert", "flat", "unlit"])
def test_renderer_outputs(shading):
    verts, faces, cams = random_scene(2, size=(24, 20))
    r = RENDERERS.build({"name": "mesh", "shading": shading, "antialias": 2,
                         "point_lights": [[0.0, 2.0, 2.0]], "background": [0.0, 0.0, 0.0]})
    out = r(Mesh(verts, faces), cams, return_timings=True)
    assert out["image"].shape == (2, 20, 24, 3) and out["alpha"].shape == (2, 20, 24)
    assert out["normals"].shape == (2, 20, 24, 3) and out["pix_to_face"].shape == (2, 20, 24)
    for k in ("image", "alpha", "depth", "normals"):
        assert torch.isfinite(out[k]).all(), k
    assert out["image"].min() >= 0 and out["image"].max() <= 1
    assert 0 < out["alpha"].mean() < 1
    assert set(out["timings"]) == {"transform", "rasterize", "shade"}
    if shading == "unlit":  # default grey-white albedo, blended with the black background
        full = out["alpha"] == 1
        expected = torch.tensor(DEFAULT_ALBEDO).expand(int(full.sum()), 3)
        torch.testing.assert_close(out["image"][full], expected)


def test_renderer_gradients_reach_texture_colours_and_vertices():
    tex = torch.rand(8, 8, 3, requires_grad=True)
    verts = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]],
                         requires_grad=True)
    uvs = (verts.detach()[:, :2] + 1) / 2
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    mesh = Mesh(verts, faces, verts_uvs=uvs, faces_uvs=faces, texture=tex)
    out = MeshRenderer(shading="phong", point_lights=[[0.5, 0.5, 2.0]])(mesh, _front_camera(16))
    (out["image"].sum() + out["depth"].sum()).backward()
    for g in (tex.grad, verts.grad):
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0


@pytest.mark.parametrize("kwargs, needle", [
    ({"ambient": -1}, "ambient must be a number >= 0"),             # render360 ambient=-1 used to render
    ({"diffuse": [0.5, -0.1, 0.5]}, "diffuse must be a number >= 0 or 3 of them"),
    ({"specular": [0.1, 0.1]}, "specular must be a number >= 0 or 3 of them"),
    ({"light_color": "white"}, "light_color must be a number >= 0 or 3 of them"),
    ({"shininess": 0}, "shininess must be > 0"),
])
def test_renderer_rejects_negative_or_malformed_material_and_light(kwargs, needle):
    from l3d_app.errors import UserError

    with pytest.raises(UserError, match=needle):
        MeshRenderer(**kwargs)
    MeshRenderer(ambient=0, diffuse=(0.2, 0.3, 0.4), specular=torch.tensor(0.0), light_color=[1, 1, 1])
