"""sds_nerf and its pieces: view-prompt blending, regularisers, density normals, shading, a tiny run."""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.diffusion.view_prompts import VIEWS, ViewPrompts, sample_orbit_cameras, view_names, view_weights
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.losses.nerf_regularizers import density_normals, opacity_entropy, orientation_penalty
from l3d_app.models.blob_field import BlobField
from l3d_app.render.volume.field_shading import normals_as_latent, shading_sampler
from l3d_app.losses.nerf_regularizers import density_normals, orientation_penalty
from l3d_app.render.volume.field_shading import render_shaded_views


def render_views(*args, **kw):
    return render_shaded_views(*args, normals_fn=density_normals, penalty_fn=orientation_penalty, **kw)
from sds_task_runs import numbers_finite, run_metrics

SMALL = ("iters=4", "eval_every=2", "eval_views=2", "num_frames=2", "n_samples=12", "image_size=16",
         "turntable_size=16", "tensorboard=false", "threads=1")


# ----------------------------------------------------------------------------- view prompts
def test_view_weights_sum_to_one_and_pick_the_named_views():
    azim = torch.tensor([0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 360.0, -90.0, 30.0, 30.0])
    elev = torch.tensor([0.0] * 9 + [75.0, -75.0])
    w = view_weights(azim, elev, overhead_deg=60.0)
    assert w.shape == (11, 5)
    assert torch.allclose(w.sum(-1), torch.ones(11)) and bool((w >= 0).all())
    eye = torch.eye(5)
    F, S, B, O, D = (eye[i] for i in range(5))
    expected = torch.stack([F, (F + S) / 2, S, (S + B) / 2, B, (S + B) / 2, S, F, S, O, D])
    assert torch.allclose(w, expected, atol=1e-6)
    assert view_names(azim, elev)[:5] == ["front", "front", "side", "side", "back"]


class _FakePrior(DiffusionPrior):
    """Embeds a prompt as a vector of its character codes (distinct prompts, distinct vectors)."""

    def __init__(self):
        super().__init__()
        self.register_buffer("alphas_cumprod", torch.linspace(0.99, 0.01, 10))

    def embed_prompt(self, prompt):
        code = torch.tensor([float(sum(map(ord, prompt))), float(len(prompt)), 1.0])
        return PromptEmbedding(cond=code[None], uncond=torch.zeros(1, 3))


def test_view_prompt_embeddings_blend_linearly():
    prior = _FakePrior()
    views = ViewPrompts.build(prior, "a chair", view_dependent=True)
    assert views.prompts == tuple(f"a chair, {v} view" for v in VIEWS)
    emb = views.embedding(torch.tensor([0.0, 45.0, 180.0, 10.0]), torch.tensor([0.0, 0.0, 0.0, 80.0]))
    front, side, back, over = (prior.embed_prompt(f"a chair, {v} view").cond[0]
                               for v in ("front", "side", "back", "overhead"))
    assert emb.cond.shape == (4, 3) and emb.uncond.shape == (1, 3)
    assert torch.allclose(emb.cond[0], front) and torch.allclose(emb.cond[2], back)
    assert torch.allclose(emb.cond[1], (front + side) / 2) and torch.allclose(emb.cond[3], over)
    plain = ViewPrompts.build(prior, "a chair", view_dependent=False, overrides={"overhead": "a seat"})
    assert plain.prompts == ("a chair",) * 3 + ("a seat", "a chair")
    with pytest.raises(UserError):
        ViewPrompts.build(prior, "a chair", overrides={"top": "x"})
    with pytest.raises(UserError):
        ViewPrompts.build(prior, "a chair", template="{prompt} only")


def test_orbit_cameras_look_at_the_origin_from_the_sampled_angles():
    g = torch.Generator().manual_seed(0)
    cams, azim, elev = sample_orbit_cameras(6, 8, g, distance=(2.0, 3.0), elevation=(-10.0, 60.0))
    assert cams.batch_size == 6 and bool(((azim >= 0) & (azim <= 360)).all())
    assert bool(((elev >= -10) & (elev <= 60)).all())
    c = cams.centers()
    assert torch.allclose(torch.rad2deg(torch.asin(c[:, 1] / c.norm(dim=-1))), elev, atol=1e-3)
    assert torch.allclose(cams.R[:, 2], -torch.nn.functional.normalize(c, dim=-1), atol=1e-5)  # optical axis to 0
    with pytest.raises(UserError):
        sample_orbit_cameras(2, 8, g, elevation=(-10.0, 95.0))
    with pytest.raises(UserError):
        sample_orbit_cameras(2, 8, g, distance=(3.0,))


# ----------------------------------------------------------------------------- regularisers
def test_entropy_is_zero_at_opacity_0_and_1_and_one_bit_at_half():
    a = torch.tensor([0.0, 1.0, 0.5, 0.1, 0.9], requires_grad=True)
    per = [float(opacity_entropy(a[i:i + 1].detach())) for i in range(5)]
    assert per[0] < 1e-3 and per[1] < 1e-3 and abs(per[2] - 1.0) < 1e-6
    ref = -(0.1 * math.log2(0.1) + 0.9 * math.log2(0.9))
    assert abs(per[3] - ref) < 1e-5 and abs(per[4] - ref) < 1e-5
    assert per[0] < per[3] < per[2]                      # minimal at the ends, maximal at 1/2
    opacity_entropy(a).backward()
    assert torch.isfinite(a.grad).all()


def test_orientation_penalty_zero_when_normals_face_the_camera():
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(100, 3, generator=g), dim=-1)
    n = torch.nn.functional.normalize(torch.randn(100, 3, generator=g), dim=-1)
    n = torch.where(((n * d).sum(-1) > 0)[:, None], -n, n)     # every normal faces the camera
    assert float(orientation_penalty(n, d).abs().max()) == 0.0
    assert torch.allclose(orientation_penalty(-n, d), (n * d).sum(-1) ** 2)   # facing away: cos^2


def test_density_normals_of_a_radial_density_point_outward():
    x = torch.tensor([[0.3, 0.0, 0.0], [0.0, -0.5, 0.2], [0.1, 0.2, -0.7]], dtype=torch.float64,
                     requires_grad=True)
    sigma = torch.exp(-(x * x).sum(-1) * 3.0)
    n = density_normals(sigma, x)
    assert torch.allclose(n, x.detach() / x.detach().norm(dim=-1, keepdim=True), atol=1e-12)
    n.sum().backward()                                   # differentiable (create_graph)
    assert torch.isfinite(x.grad).all()


class _Ball(torch.nn.Module):
    """A soft opaque ball of radius 0.5 with one learnable colour."""

    def __init__(self):
        super().__init__()
        self.colour = torch.nn.Parameter(torch.tensor([0.2, 0.4, 0.6]))

    def density(self, x):
        return 200.0 * torch.sigmoid((0.5 - x.norm(dim=-1)) * 40.0)

    def forward(self, x, d):
        return self.density(x), self.colour.expand(x.shape[0], 3)


def test_rendered_ball_faces_the_camera_and_shades_as_expected():
    field = BlobField(_Ball(), blob_density=0.0)
    cams = look_at_cameras(3.0, 0.0, 0.0, 40.0, 16)
    kw = dict(n_samples=128, background=[1.0, 1.0, 1.0], ambient=0.3)
    albedo = render_views(field, cams, "albedo", **kw)
    centre = albedo["opacity"][0, 8, 8]
    assert float(centre) > 0.999 and float(albedo["opacity"][0, 0, 0]) < 1e-3
    assert torch.allclose(albedo["image"][0, 8, 8], torch.tensor([0.2, 0.4, 0.6]), atol=1e-3)
    assert torch.allclose(albedo["image"][0, 0, 0], torch.ones(3), atol=1e-3)       # background
    lit = render_views(field, cams, "textureless", **kw)
    # headlight on the sphere's centre pixel: n . l ~ 1, so ambient + (1 - ambient) * 1 = 1
    assert abs(float(lit["image"][0, 8, 8, 0]) - 1.0) < 0.02
    # only camera-facing normals are visible inside the silhouette (grazing rays at its rim
    # pass the tangent point through the soft shell and see a little of the far side)
    inside = lit["opacity"] > 0.99
    assert float(lit["orient"][inside].abs().max()) < 1e-4 and float(lit["orient"].abs().max()) < 0.02
    assert torch.isfinite(lit["normal"]).all()
    # training render: gradients reach the field's parameters, finite
    out = render_views(field, cams, "lambertian", training=True, generator=torch.Generator().manual_seed(0), **kw)
    (out["image"].sum() + out["orient"].sum()).backward()
    assert field.field.colour.grad is not None and torch.isfinite(field.field.colour.grad).all()
    latent = normals_as_latent(out)
    assert latent.shape == (1, 4, 16, 16) and float(latent.detach().abs().max()) <= 1.0 + 1e-5


def test_shading_sampler_respects_probabilities_and_rejects_bad_names():
    g = torch.Generator().manual_seed(0)
    draw = shading_sampler({"albedo": 0.0, "textureless": 1.0})
    assert {draw(g) for _ in range(20)} == {"textureless"}
    draw = shading_sampler({"albedo": 1.0, "lambertian": 1.0})
    counts = [draw(g) for _ in range(400)].count("albedo")
    assert 150 < counts < 250
    with pytest.raises(UserError):
        shading_sampler({"shiny": 1.0})
    with pytest.raises(UserError):
        shading_sampler({"albedo": 0.0})


# ----------------------------------------------------------------------------- the task
def _run(compose, tmp_path, *overrides):
    return run_metrics(compose, tmp_path, "task=sds_nerf", *SMALL, *overrides)



def test_sds_nerf_tiny_run_writes_outputs_with_finite_metrics(compose, tmp_path):
    m = _run(compose, tmp_path)
    assert (tmp_path / "sds_nerf.gif").exists() and (tmp_path / "views.png").exists()
    assert m["iters"] == 4 and m["latent_iters"] == 0 and numbers_finite(m)
    for key in ("match_rate", "opacity", "opacity_entropy", "orientation", "seconds", "seconds_per_iter"):
        assert key in m
    assert m["view_prompts"]["front"] == "a red circle on white"      # built-in prior: no view words
    assert 0.0 <= m["opacity"] <= 1.0


def test_sds_nerf_latent_iterations_with_the_latent_prior(compose, tmp_path):
    m = _run(compose, tmp_path, "space=latent", "latent_iter_ratio=0.5")
    assert m["latent_iters"] == 2 and m["iters"] == 4 and numbers_finite(m)


def test_sds_nerf_rejects_bad_knobs(compose, tmp_path):
    with pytest.raises(UserError):
        _run(compose, tmp_path, "latent_iter_ratio=1.5")
    with pytest.raises(UserError):
        _run(compose, tmp_path, "shading_probs.albedo=-1")
    with pytest.raises(UserError):   # the built-in vocabulary has no view words
        _run(compose, tmp_path, "view_dependent=true")


def test_sds_nerf_interrupt_and_resume_equals_an_uninterrupted_run(compose, tmp_path, monkeypatch):
    from l3d_app.app import RunInterrupted

    whole, parts = tmp_path / "whole", tmp_path / "parts"
    small = ("iters=4", "sampler.update_every=2")          # the grid changes across the cut
    _run(compose, whole, *small)
    monkeypatch.setenv("L3D_STOP_AT_STEP", "2")
    with pytest.raises(RunInterrupted):
        _run(compose, parts, *small)
    monkeypatch.delenv("L3D_STOP_AT_STEP")
    m = _run(compose, parts, *small, "resume=true")
    assert m["iters"] == 4
    a, b = (torch.load(d / "checkpoint.pt", weights_only=False)["trainable"] for d in (whole, parts))
    assert all(torch.equal(a["modules"]["field"][k], b["modules"]["field"][k]) for k in a["modules"]["field"])
    assert torch.equal(a["extra"]["sampler"]["grid.mask"], b["extra"]["sampler"]["grid.mask"])
