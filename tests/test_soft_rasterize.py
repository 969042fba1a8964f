"""Soft rasteriser: gradients, limits, a dense naive reference, hard cases, a tiny fit."""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.geometry.cameras import Cameras, look_at
from l3d_app.geometry.mesh import Mesh
from l3d_app.registry import RENDERERS
from l3d_app.render.mesh.soft_rasterize import SoftMeshRenderer, influence_radius, soft_rasterize

F64 = torch.float64


# ------------------------------------------------------------------ helpers
def front_cameras(width, height, dist=3.0, focal=None, dtype=F64):
    """One camera at world (0, 0, -dist) looking along +Z (R = I), principal point centred."""
    f = focal if focal is not None else 0.6 * min(width, height)
    return Cameras(torch.eye(3, dtype=dtype), torch.tensor([0.0, 0.0, dist], dtype=dtype),
                   f, f, width / 2.0, height / 2.0, width, height)


def orbit_cameras(width, height, azim=(10.0, -35.0), elev=(15.0, -20.0), dist=3.0, dtype=F64):
    R, t = look_at(dist, elev, azim, dtype=dtype)
    f = 0.9 * min(width, height)
    return Cameras(R, t, f, f, width / 2.0 + 0.3, height / 2.0 - 0.2, width, height)


def random_mesh(n_faces, seed, spread=0.8, dtype=F64):
    """Independent random triangles (3 * n_faces vertices) of moderate size."""
    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(n_faces, 1, 3, generator=g, dtype=dtype) - 0.5) * 2 * spread
    offsets = (torch.rand(n_faces, 3, 3, generator=g, dtype=dtype) - 0.5) * 0.9
    verts = (centres + offsets).reshape(-1, 3)
    faces = torch.arange(3 * n_faces).reshape(n_faces, 3)
    return verts, faces


def _seg_d2(p, a, b):
    """Squared distance from points p (..., 2) to segment ab, written plainly."""
    ab, ap = b - a, p - a
    t = ((ap * ab).sum(-1) / (ab * ab).sum()).clamp(0, 1)
    closest = a + t[..., None] * ab
    return ((p - closest) ** 2).sum(-1)


def _cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def dense_reference(cams, verts, faces, *, vert_colors=None, face_colors=None, texture=None,
                    verts_uvs=None, faces_uvs=None, sigma, gamma, background=(0.0, 0.0, 0.0),
                    near=0.1, far=100.0, dist_eps=1e-4, background_eps=1e-3):
    """Every face x every pixel, products and softmax taken literally (no logs, no max).

    Loops over views and faces; use only with moderate gamma (exp(1 / gamma) finite).
    """
    H, W = cams.height, cams.width
    uv, z = cams.project(verts)
    B = uv.shape[0]
    jj, ii = torch.meshgrid(torch.arange(W, dtype=uv.dtype) + 0.5,
                            torch.arange(H, dtype=uv.dtype) + 0.5, indexing="xy")
    p = torch.stack([jj, ii], -1)                                      # (H, W, 2)
    ndc2 = (2.0 / min(H, W)) ** 2
    bg = torch.as_tensor(background, dtype=uv.dtype)
    sils, imgs = [], []
    for b in range(B):
        prod = torch.ones(H, W, dtype=uv.dtype)
        w_bg = math.exp(background_eps / gamma)
        num, den = w_bg * bg.expand(H, W, 3), torch.full((H, W), w_bg, dtype=uv.dtype)
        for f in range(faces.shape[0]):
            idx = faces[f]
            A, Bv, C = uv[b, idx[0]], uv[b, idx[1]], uv[b, idx[2]]
            zf = z[b, idx]
            area2 = _cross(Bv - A, C - A)
            size = ((Bv - A) ** 2).sum() + ((C - Bv) ** 2).sum() + ((A - C) ** 2).sum()
            zmin = float(zf.detach().min())
            if zmin < near or zmin > far or abs(float(area2.detach())) <= 1e-9 * float(size.detach()):
                continue
            d2 = torch.minimum(torch.minimum(_seg_d2(p, A, Bv), _seg_d2(p, Bv, C)), _seg_d2(p, C, A))
            lam = torch.stack([_cross(Bv - p, C - p), _cross(C - p, A - p), _cross(A - p, Bv - p)], -1) / area2
            inside = (lam >= 0).all(-1)
            D = torch.sigmoid(torch.where(inside, d2, -d2) * ndc2 / sigma)
            D = torch.where(D >= dist_eps, D, torch.zeros_like(D))
            prod = prod * (1 - D)
            lam = lam.clamp(0, 1)
            lam = lam / lam.sum(-1, keepdim=True)
            zp = 1.0 / (lam / zf).sum(-1)
            pw = lam / zf * zp[..., None]                               # perspective-correct
            if vert_colors is not None:
                vc = vert_colors if vert_colors.dim() == 2 else vert_colors[b]
                col = (pw[..., None] * vc[idx]).sum(-2)
            elif face_colors is not None:
                col = face_colors[f].expand(H, W, 3)
            elif texture is None:
                col = torch.zeros(H, W, 3, dtype=uv.dtype)
            else:
                uvf = (pw[..., None] * verts_uvs[faces_uvs[f]]).sum(-2)  # (H, W, 2), v up
                grid = torch.stack([2 * uvf[..., 0] - 1, 1 - 2 * uvf[..., 1]], -1)[None]
                col = torch.nn.functional.grid_sample(
                    texture.permute(2, 0, 1)[None], grid, mode="bilinear",
                    padding_mode="border", align_corners=False)[0].permute(1, 2, 0)
            wgt = D * torch.exp((far - zp) / (far - near) / gamma)
            num = num + wgt[..., None] * col
            den = den + wgt
        sils.append(1 - prod)
        imgs.append(num / den[..., None])
    return {"silhouette": torch.stack(sils), "image": torch.stack(imgs)}


def _quad(dtype=F64):
    """Two triangles of a slanted quad (different depths per vertex), 4 vertices."""
    verts = torch.tensor([[-0.9, -0.7, 0.1], [0.8, -0.8, -0.2], [0.7, 0.75, 0.3], [-0.61, 0.93, 0.05]],
                         dtype=dtype)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return verts, faces


# ------------------------------------------------------------ (a) gradcheck
def test_gradcheck_silhouette_wrt_vertices():
    cams = front_cameras(6, 5, focal=4.0)
    verts, faces = _quad()
    verts = verts.requires_grad_()
    fn = lambda v: soft_rasterize(cams, v, faces, sigma=3e-2, dist_eps=1e-9)["silhouette"]  # noqa: E731
    assert torch.autograd.gradcheck(fn, (verts,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_colour_wrt_vertices_and_vertex_colours():
    cams = front_cameras(6, 6, focal=4.0)
    verts, faces = _quad()
    colors = torch.rand(4, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    args = (verts.clone().requires_grad_(), colors.requires_grad_())
    fn = lambda v, c: soft_rasterize(cams, v, faces, vert_colors=c, sigma=3e-2, gamma=0.2,  # noqa: E731
                                     background=(0.2, 0.5, 0.9), dist_eps=1e-9)["image"]
    assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_colour_wrt_texture_uvs_and_vertices():
    cams = front_cameras(6, 6, focal=4.0)
    verts, faces = _quad()
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(3, 4, 3, generator=g, dtype=F64)
    vuv = torch.tensor([[0.1, 0.15], [0.85, 0.2], [0.9, 0.8], [0.2, 0.9]], dtype=F64)
    fuv = faces.clone()
    args = (verts.clone().requires_grad_(), tex.requires_grad_(), vuv.requires_grad_())
    fn = lambda v, t, u: soft_rasterize(cams, v, faces, texture=t, verts_uvs=u, faces_uvs=fuv,  # noqa: E731
                                        sigma=3e-2, gamma=0.2, dist_eps=1e-9)["image"]
    assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-6, rtol=1e-4)


# --------------------------------------------- (b) limit: hard rasterisation
def _hard_inside_and_margin(cams, verts, tri):
    """Hard coverage of one triangle and each pixel's distance (px) to its edge LINES."""
    uv, _ = cams.project(verts)
    H, W = cams.height, cams.width
    jj, ii = torch.meshgrid(torch.arange(W, dtype=uv.dtype) + 0.5,
                            torch.arange(H, dtype=uv.dtype) + 0.5, indexing="xy")
    p = torch.stack([jj, ii], -1)
    a, b, c = uv[0, tri[0]], uv[0, tri[1]], uv[0, tri[2]]
    s = torch.sign(_cross(b - a, c - a))
    edges = [(a, b), (b, c), (c, a)]
    signed = torch.stack([s * _cross(q - o, p - o) / (q - o).norm() for o, q in edges], -1)
    return (signed > 0).all(-1), signed.abs().amin(-1)


def test_small_sigma_gamma_converge_to_hard_rasterisation():
    cams = front_cameras(48, 40, dtype=torch.float32)
    # a red triangle in front (z = -0.5) partly covering a green one behind (z = +0.5)
    verts = torch.tensor([[-0.8, -0.6, -0.5], [0.6, -0.4, -0.5], [0.0, 0.7, -0.5],
                          [-0.3, -0.9, 0.5], [1.1, 0.1, 0.5], [-0.2, 0.8, 0.5]])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    colors = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]])
    bg = (0.0, 0.0, 1.0)
    in_front, m0 = _hard_inside_and_margin(cams, verts, faces[0])
    in_back, m1 = _hard_inside_and_margin(cams, verts, faces[1])
    hard = in_front | in_back
    clear = (m0 > 0.25) & (m1 > 0.25)                 # pixel centres 1/4 px from every edge line
    assert clear.sum() > 300 and hard[clear].any() and (~hard[clear]).any()
    errors = []
    for sigma in (1e-3, 1e-5, 1e-7):
        out = soft_rasterize(cams, verts, faces, face_colors=colors, sigma=sigma, gamma=1e-5,
                             background=bg)
        sil, img = out["silhouette"][0], out["image"][0]
        errors.append(float((sil - hard.float())[clear].abs().max()))
    assert errors[0] > 0.05 and errors[-1] < 1e-5 and errors[1] < errors[0]
    want = torch.where(in_front[..., None], colors[0], torch.where(in_back[..., None], colors[1],
                                                                    torch.tensor(bg)))
    assert torch.allclose(img[clear], want[clear], atol=1e-5)
    assert (in_front & in_back & clear).sum() > 25   # the z-test was really exercised


# ---------------------------------------------- (c) against the dense reference
@pytest.mark.parametrize("colour", ["vert", "face", "texture"])
def test_matches_dense_reference_values_and_gradients(colour):
    cams = orbit_cameras(16, 12)
    verts, faces = random_mesh(7, seed=3)
    g = torch.Generator().manual_seed(4)
    kw = dict(sigma=1.5e-2, gamma=5e-2, background=(0.3, 0.6, 0.1), near=0.5, far=6.0)
    leaves = [verts.requires_grad_()]
    if colour == "vert":
        kw["vert_colors"] = torch.rand(verts.shape[0], 3, generator=g, dtype=F64).requires_grad_()
        leaves.append(kw["vert_colors"])
    elif colour == "face":
        kw["face_colors"] = torch.rand(faces.shape[0], 3, generator=g, dtype=F64).requires_grad_()
        leaves.append(kw["face_colors"])
    else:
        kw["texture"] = torch.rand(5, 7, 3, generator=g, dtype=F64).requires_grad_()
        kw["verts_uvs"] = torch.rand(verts.shape[0], 2, generator=g, dtype=F64).requires_grad_()
        kw["faces_uvs"] = faces
        leaves += [kw["texture"], kw["verts_uvs"]]
    wsil = torch.rand(2, 12, 16, generator=g, dtype=F64)
    wimg = torch.rand(2, 12, 16, 3, generator=g, dtype=F64)

    def values_and_grads(fn, **extra):
        out = fn(cams, verts, faces, **kw, **extra)
        loss = (out["silhouette"] * wsil).sum() + (out["image"] * wimg).sum()
        return out, torch.autograd.grad(loss, leaves)

    ref, ref_grads = values_and_grads(dense_reference)
    assert 0.05 < ref["silhouette"].mean() < 0.95        # a non-trivial scene
    for extra in (dict(max_pairs=37), dict(max_pairs=1 << 20), dict(max_pairs=101, checkpoint=True)):
        out, grads = values_and_grads(soft_rasterize, **extra)
        for key in ("silhouette", "image"):
            torch.testing.assert_close(out[key], ref[key], rtol=1e-10, atol=1e-10)
        for got, want in zip(grads, ref_grads):
            assert want.abs().max() > 1e-3
            torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-9)


def test_float32_sharp_settings_match_float64_reference():
    cams = orbit_cameras(24, 20)
    verts, faces = random_mesh(10, seed=11)
    colors = torch.rand(verts.shape[0], 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    kw = dict(sigma=1e-3, gamma=2e-2, near=0.5, far=6.0)
    ref = dense_reference(cams, verts, faces, vert_colors=colors, **kw)
    out = soft_rasterize(cams.to(dtype=torch.float32), verts.float(), faces,
                         vert_colors=colors.float(), **kw)
    assert out["silhouette"].dtype == torch.float32
    torch.testing.assert_close(out["silhouette"].double(), ref["silhouette"], rtol=0, atol=2e-4)
    torch.testing.assert_close(out["image"].double(), ref["image"], rtol=0, atol=2e-3)


def test_batched_vertices_and_cameras_match_single_views():
    cams = orbit_cameras(10, 9)
    verts, faces = random_mesh(5, seed=7)
    verts_b = torch.stack([verts, verts.flip(0) * 0.9])
    colors = torch.rand(2, verts.shape[0], 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    kw = dict(sigma=1e-2, gamma=1e-2)
    out = soft_rasterize(cams, verts_b, faces, vert_colors=colors, **kw)
    for b in range(2):
        one = soft_rasterize(cams[b], verts_b[b], faces, vert_colors=colors[b], **kw)
        torch.testing.assert_close(out["image"][b], one["image"][0])
        torch.testing.assert_close(out["silhouette"][b], one["silhouette"][0])
    shared = soft_rasterize(cams, verts[None], faces, vert_colors=colors[0], **kw)   # (1, V, 3)
    for b in range(2):
        one = soft_rasterize(cams[b], verts, faces, vert_colors=colors[0], **kw)
        torch.testing.assert_close(shared["image"][b], one["image"][0])


def test_truncation_drops_exactly_the_coverage_below_dist_eps():
    cams = front_cameras(40, 36)
    verts = torch.tensor([[-0.5, -0.5, 0.0], [0.5, -0.4, 0.0], [0.1, 0.5, 0.0]], dtype=F64)
    faces = torch.tensor([[0, 1, 2]])
    full = dense_reference(cams, verts, faces, sigma=1e-2, gamma=1.0, dist_eps=1e-300)["silhouette"]
    for dist_eps in (1e-1, 1e-2, 1e-4):
        sil = soft_rasterize(cams, verts, faces, sigma=1e-2, dist_eps=dist_eps)["silhouette"]
        want = torch.where(full >= dist_eps, full, torch.zeros_like(full))
        torch.testing.assert_close(sil, want, rtol=1e-12, atol=1e-15)
        assert ((full > 0.5 * dist_eps) & (full < dist_eps)).any()   # pixels really dropped
    assert influence_radius(1e-4, 1e-4) == pytest.approx(math.sqrt(1e-4 * math.log(9999)))


# ---------------------------------------------------------- (d) hard cases
def _finite_grads(out, leaves):
    loss = out["silhouette"].sum() + out.get("image", torch.zeros(())).sum()
    grads = torch.autograd.grad(loss, leaves)
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    return grads


def test_degenerate_faces_contribute_nothing():
    cams = front_cameras(16, 16)
    good = torch.tensor([[-0.5, -0.5, 0.0], [0.5, -0.4, 0.1], [0.0, 0.6, 0.0]], dtype=F64)
    collinear = torch.tensor([[-0.7, -0.7, 0.0], [0.0, 0.0, 0.0], [0.7, 0.7, 0.0]], dtype=F64)
    point = torch.tensor([[0.2, 0.1, 0.0]] * 3, dtype=F64)
    edge_on = torch.tensor([[0.0, -0.5, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.8]], dtype=F64)  # plane x=0
    verts = torch.cat([good, collinear, point, edge_on]).requires_grad_()
    colors = torch.rand(12, 3, generator=torch.Generator().manual_seed(0), dtype=F64).requires_grad_()
    faces = torch.arange(12).reshape(4, 3)
    kw = dict(sigma=1e-3, gamma=1e-3, background=(1.0, 1.0, 1.0))
    out = soft_rasterize(cams, verts, faces, vert_colors=colors, **kw)
    only = soft_rasterize(cams, good, faces[:1], vert_colors=colors[:3].detach(), **kw)
    torch.testing.assert_close(out["silhouette"], only["silhouette"])
    torch.testing.assert_close(out["image"], only["image"])
    gv, gc = _finite_grads(out, [verts, colors])
    assert gv[3:].abs().max() == 0 and gc[3:].abs().max() == 0 and gv[:3].abs().max() > 0


def test_faces_crossing_the_near_plane_are_culled():
    cams = front_cameras(16, 16)                       # camera centre at world z = -3
    verts = torch.tensor([[-0.5, -0.5, -3.5], [0.5, -0.5, 0.0], [0.0, 0.5, 0.0],   # one behind
                          [-0.5, 0.5, -3.0], [0.5, 0.5, 0.0], [0.0, -0.5, 0.0],    # one at Z = 0
                          [-0.3, -0.3, -2.95], [0.3, -0.3, 0.0], [0.0, 0.3, 0.0]],  # Z = 0.05 < near
                         dtype=F64, requires_grad=True)
    faces = torch.arange(9).reshape(3, 3)
    colors = torch.rand(9, 3, dtype=F64, requires_grad=True)
    out = soft_rasterize(cams, verts, faces, vert_colors=colors, near=0.1, sigma=1e-4, gamma=1e-4)
    assert out["silhouette"].abs().max() == 0
    assert torch.all(out["image"] == 0)
    gv, gc = _finite_grads(out, [verts, colors])
    assert gv.abs().max() == 0 and gc.abs().max() == 0
    # just in front of the near plane: kept, covers the whole image, stays finite
    verts2 = torch.tensor([[-5.0, -5.0, -2.85], [5.0, -5.0, -2.85], [0.0, 5.0, -2.85]], dtype=F64,
                          requires_grad=True)
    out2 = soft_rasterize(cams, verts2, faces[:1], vert_colors=colors[:3], near=0.1)
    assert out2["silhouette"].min() > 0.99
    _finite_grads(out2, [verts2])


def test_mesh_outside_the_view_gives_background_and_zero_gradients():
    cams = front_cameras(12, 10, dtype=torch.float32)
    verts, faces = random_mesh(4, seed=0, dtype=torch.float32)
    for shift in ([30.0, 0.0, 0.0], [0.0, 0.0, 500.0], [0.0, 0.0, -10.0]):   # aside, beyond far, behind
        v = (verts + torch.tensor(shift)).requires_grad_()
        tex = torch.rand(4, 4, 3, requires_grad=True)
        out = soft_rasterize(cams, v, faces, texture=tex, verts_uvs=torch.rand(12, 2),
                             faces_uvs=faces, background=(0.1, 0.2, 0.3))
        assert torch.all(out["silhouette"] == 0)
        assert torch.allclose(out["image"], torch.tensor([0.1, 0.2, 0.3]).expand(1, 10, 12, 3))
        gv, gt = _finite_grads(out, [v, tex])
        assert gv.abs().max() == 0 and gt.abs().max() == 0


@pytest.mark.parametrize("sigma,gamma", [(1e-10, 1e-10), (1e-4, 1e-4), (10.0, 100.0)])
def test_extreme_sigma_gamma_stay_finite_float32(sigma, gamma):
    cams = orbit_cameras(20, 16, dtype=torch.float32)
    verts, faces = random_mesh(12, seed=5, dtype=torch.float32)
    verts.requires_grad_()
    colors = torch.rand(verts.shape[0], 3, requires_grad=True)
    out = soft_rasterize(cams, verts, faces, vert_colors=colors, sigma=sigma, gamma=gamma)
    assert torch.isfinite(out["silhouette"]).all() and torch.isfinite(out["image"]).all()
    assert out["silhouette"].min() >= 0 and out["silhouette"].max() <= 1
    assert out["image"].min() >= -1e-6 and out["image"].max() <= 1 + 1e-6
    gv, gc = _finite_grads(out, [verts, colors])
    assert gc.abs().max() > 0


def test_invalid_arguments_are_user_errors():
    from l3d_app.errors import UserError
    cams = front_cameras(4, 4)
    verts, faces = _quad()
    with pytest.raises(UserError):
        soft_rasterize(cams, verts, faces, near=0.0)
    with pytest.raises(UserError):
        soft_rasterize(cams, verts, faces, sigma=0.0)
    with pytest.raises(UserError):
        soft_rasterize(cams, verts, faces, vert_colors=verts, face_colors=verts[:2])
    with pytest.raises(UserError):
        soft_rasterize(cams, verts, faces, texture=torch.rand(2, 2, 3))
    with pytest.raises(UserError):
        soft_rasterize(cams, verts, faces + 1)
    with pytest.raises(UserError):
        soft_rasterize(orbit_cameras(4, 4), torch.stack([verts] * 3), faces)


# ------------------------------------------------------- (e) a tiny fit
def test_adam_on_silhouette_loss_recovers_an_offset_triangle():
    torch.manual_seed(0)
    cams = front_cameras(32, 32, dtype=torch.float32)
    target_verts = torch.tensor([[-0.6, -0.5, 0.0], [0.7, -0.3, 0.0], [0.0, 0.6, 0.0]])
    faces = torch.tensor([[0, 1, 2]])
    kw = dict(sigma=1e-3)
    target = soft_rasterize(cams, target_verts, faces, **kw)["silhouette"]
    verts = (target_verts + torch.tensor([0.15, -0.1, 0.0])).requires_grad_()
    opt = torch.optim.Adam([verts], lr=0.02)
    losses = []
    for _ in range(40):
        loss = ((soft_rasterize(cams, verts, faces, **kw)["silhouette"] - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.1 * losses[0]
    assert (verts.detach() - target_verts)[:, :2].abs().max() < 0.08   # started 0.15 off


# ----------------------------------------------------------- the renderer
def test_soft_mesh_renderer_from_registry():
    renderer = RENDERERS.build({"name": "soft_mesh", "sigma": 1e-4, "gamma": 1e-4,
                                "background": [1.0, 1.0, 1.0]})
    assert isinstance(renderer, SoftMeshRenderer)
    cams = orbit_cameras(16, 16, dtype=torch.float32)
    verts, faces = random_mesh(6, seed=1, dtype=torch.float32)
    for mesh in (Mesh(verts, faces),
                 Mesh(verts, faces, vert_colors=torch.rand(verts.shape[0], 3)),
                 Mesh(verts, faces, verts_uvs=torch.rand(verts.shape[0], 2), faces_uvs=faces,
                      texture=torch.rand(8, 8, 3))):
        out = renderer(mesh, cams)
        assert out["image"].shape == (2, 16, 16, 3) and out["alpha"].shape == (2, 16, 16)
        assert out["alpha"].max() > 0.9 and torch.isfinite(out["image"]).all()
    plain = renderer(Mesh(verts, faces), cams)
    grey, covered = plain["image"], plain["alpha"] > 0.99
    assert torch.allclose(grey[covered], torch.full_like(grey[covered], 0.5))
