"""SVR encoder and decoders: shapes, finite losses and gradients, analytic pieces, a tiny overfit."""

from __future__ import annotations

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.primitives import icosphere
from l3d_app.geometry.point_mesh_distance import point_mesh_distance
from l3d_app.losses.mesh_regularizers import laplacian_smoothing
from l3d_app.models.svr_decoders import sample_meshes
from l3d_app.models.svr_encoder import ImageEncoder
from l3d_app.models.svr_pseudo import fixed_cameras
from l3d_app.losses.svr import svr_loss
from l3d_app.models.svr_model import build_svr_model as build_model

GEOM = {"voxel_size": 16, "distance": 2.5, "fov": 50.0, "image_size": 16}
ENC = {"width": 8, "max_width": 32, "latent_dim": 32}
DECODERS = [{"name": "svr_vox", "width": 16, "pos_weight": 3.0},
            {"name": "svr_point", "num_points": 64, "hidden": [32], "target_points": 50},
            {"name": "svr_mesh", "ico_level": 1, "hidden": [32], "num_samples": 64, "w_smooth": 0.5},
            {"name": "svr_implicit", "hidden": 16, "layers": 2, "queries": 40, "mesh_resolution": 8},
            {"name": "svr_pseudo", "depth_size": 8, "width": 16, "views_per_step": 2}]


def fake_batch(B=2, g=None):
    g = g or torch.Generator().manual_seed(0)
    S = 3
    cams = look_at_cameras(2.5, torch.tensor([0.0, 30.0, -10.0]), torch.tensor([0.0, 100.0, 220.0]), 50.0, 16)
    depth = torch.where(torch.rand(B, S, 16, 16, generator=g) > 0.6, 2.0 + torch.rand(B, S, 16, 16, generator=g), 0.0)
    return {"images": torch.rand(B, 16, 16, 3, generator=g), "points": torch.rand(B, 100, 3, generator=g) - 0.5,
            "voxels": torch.rand(B, 16, 16, 16, generator=g) > 0.9, "occ_points": torch.rand(B, 60, 3, generator=g) * 2 - 1,
            "occ_labels": torch.rand(B, 60, generator=g) > 0.7, "depth": depth, "depth_cameras": cams}


def test_encoder_shapes_and_errors():
    for size in (16, 32, 64):
        enc = ImageEncoder(size, width=8, max_width=32, latent_dim=24)
        assert enc(torch.rand(3, size, size, 3)).shape == (3, 24)
    with pytest.raises(UserError):
        ImageEncoder(4)
    with pytest.raises(UserError, match="expects"):
        ImageEncoder(16)(torch.rand(2, 3, 16, 16))


@pytest.mark.parametrize("dec", DECODERS, ids=lambda d: d["name"])
def test_decoder_loss_grads_and_points(dec):
    torch.manual_seed(0)
    model = build_model(ENC, dec, GEOM)
    batch = fake_batch()
    g = torch.Generator().manual_seed(1)
    logs = svr_loss(model.decoder, model(batch["images"]), batch, g)
    assert torch.isfinite(logs["loss"]) and logs["loss"].dim() == 0
    logs["loss"].backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(gr).all() for gr in grads)
    assert sum(float(gr.abs().sum()) for gr in grads) > 0
    with torch.no_grad():
        f = model(batch["images"])
        pts = model.decoder.points(f, 30, g)
        shapes = model.decoder.shapes(f)
    assert len(pts) == 2 and len(shapes) == 2
    for p in pts:
        assert p.dim() == 2 and p.shape[1] == 3 and torch.isfinite(p).all()
        assert p.shape[0] == 0 or float(p.abs().max()) <= 3.6


def test_output_shapes():
    f = torch.randn(2, 32)
    m = {d["name"]: build_model(ENC, d, GEOM).decoder for d in DECODERS}
    assert m["svr_vox"](f).shape == (2, 16, 16, 16)
    assert m["svr_point"](f).shape == (2, 64, 3)
    assert m["svr_mesh"](f).shape == (2, 42, 3)
    assert m["svr_implicit"](f, torch.rand(2, 7, 3)).shape == (2, 7)
    out = m["svr_pseudo"](f)
    assert out["depth"].shape == (2, 8, 8, 8) and out["points"].shape == (2, 8 * 64, 3)
    with pytest.raises(UserError, match="voxel_size"):
        build_model(ENC, DECODERS[0], {**GEOM, "voxel_size": 12})


def test_mesh_decoder_starts_from_the_sphere():
    dec = build_model(ENC, DECODERS[2], GEOM).decoder
    v = dec(torch.randn(3, 32))
    assert torch.allclose(v.norm(dim=-1), torch.full((3, 42), 0.5), atol=1e-6)


def test_pseudo_points_reproject_to_their_pixels():
    """Fused points of fixed view k project back to that view's pixel centres at the predicted depth."""
    dec = build_model(ENC, DECODERS[4], GEOM).decoder
    out = dec(torch.randn(1, 32))
    cams = fixed_cameras(2.5, 50.0, 8)
    pts = out["points"].view(8, 64, 3)
    uv, z = cams.project(pts)
    j, i = torch.meshgrid(torch.arange(8) + 0.5, torch.arange(8) + 0.5, indexing="xy")
    assert torch.allclose(uv[..., 0], j.reshape(1, -1).expand(8, -1), atol=1e-4)
    assert torch.allclose(uv[..., 1], i.reshape(1, -1).expand(8, -1), atol=1e-4)
    assert torch.allclose(z, out["depth"].view(8, 64), atol=1e-5)
    assert float((out["depth"] - 2.5).abs().max().detach()) <= 1.0


def test_batched_mesh_sampling_and_laplacian():
    sphere = icosphere(2, 0.7)
    verts = torch.stack([sphere.verts, sphere.verts * 1.5 + 0.1]).requires_grad_(True)
    s = sample_meshes(verts, sphere.faces, 500, torch.Generator().manual_seed(0))
    for b in range(2):
        d = point_mesh_distance(s[b].detach(), sphere.with_verts(verts[b].detach()))[0]
        assert float(d.max()) < 1e-5
    s.sum().backward()
    assert torch.isfinite(verts.grad).all()
    # the (V, B*3) trick equals the mean of per-mesh Laplacian terms
    V = verts.shape[1]
    batched = laplacian_smoothing(verts.permute(1, 0, 2).reshape(V, 6), sphere.faces) / 2
    loop = (laplacian_smoothing(verts[0], sphere.faces) + laplacian_smoothing(verts[1], sphere.faces)) / 2
    assert torch.allclose(batched, loop, rtol=1e-6)


def test_tiny_overfit_point_decoder():
    torch.manual_seed(0)
    model = build_model(ENC, DECODERS[1], GEOM)
    batch = fake_batch()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        opt.zero_grad()
        loss = svr_loss(model.decoder, model(batch["images"]), batch, torch.Generator().manual_seed(0))["loss"]
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]
