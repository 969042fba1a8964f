"""SDS loss numerics on a tiny deterministic fake prior (exact gradients, guidance, NaN guard)."""

from __future__ import annotations

import pytest
import torch

from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.diffusion.schedule import alphas_cumprod
from l3d_app.losses.sds import (NonFiniteSDSGradient, SDSLoss, guided_noise, rgb_to_model_space,
                                sds_loss, timestep_range)


class FakePrior(DiffusionPrior):
    """eps(x_t, t, c) = a * x_t + c (per channel) + t / T, with a learnable-looking weight."""

    def __init__(self, T: int = 100, C: int = 3, size: int = 8, nan: bool = False):
        super().__init__()
        self.register_buffer("alphas_cumprod", alphas_cumprod(T, "linear"))
        self.latent_shape, self.image_size = (C, size, size), size
        self.a = torch.nn.Parameter(torch.tensor(0.5))
        self.nan, self.calls = nan, []

    def embed_prompt(self, prompt):
        cond = torch.tensor([[1.0, -2.0, 0.5]])
        return PromptEmbedding(cond=cond, uncond=torch.zeros(1, 3))

    def predict_noise(self, x_t, t, condition):
        self.calls.append(x_t.shape[0])
        out = self.a * x_t + condition.view(-1, 3, 1, 1) + t.view(-1, 1, 1, 1).float() / self.num_timesteps
        if self.nan:
            out = out.clone()
            out[0, 0, 0, 0] = float("nan")
        return out

    def encode(self, images):
        return images * 2 - 1

    def decode(self, z):
        return (z + 1) / 2


def reference_grad(prior, x, emb, s, t, noise):
    """w(t) (eps_hat - eps) in float64, written out independently of the library."""
    abar = prior.alphas_cumprod.double()[t].view(-1, 1, 1, 1)
    x0, n = x.detach().double(), noise.double()
    x_t = abar.sqrt() * x0 + (1 - abar).sqrt() * n
    a = float(prior.a)
    tt = t.double().view(-1, 1, 1, 1) / prior.num_timesteps
    eps_c = a * x_t + emb.cond.double().view(1, 3, 1, 1) + tt
    eps_u = a * x_t + emb.uncond.double().view(1, 3, 1, 1) + tt
    eps_hat = eps_u + s * (eps_c - eps_u)
    return (1 - abar) * (eps_hat - n)


@pytest.fixture
def setup():
    g = torch.Generator().manual_seed(0)
    prior = FakePrior().freeze()
    x = torch.randn(4, 3, 8, 8, generator=g).requires_grad_(True)
    emb = prior.embed_prompt("a red circle")
    return prior, x, emb, g


def _sds_and_reference(setup, scale, t):
    """``sds_loss`` at guidance ``scale`` and timesteps ``t`` with seeded noise, backpropagated into ``x``;
    returns its output and the float64 reference gradient."""
    prior, x, emb, g = setup
    noise = torch.randn(x.shape, generator=g)
    out = sds_loss(prior, x, emb, guidance_scale=scale, t=t, noise=noise)
    out.loss.backward()
    return out, reference_grad(prior, x, emb, scale, t, noise)


def test_gradient_is_weighted_noise_residual(setup):
    prior, x, _, _ = setup
    t = torch.tensor([0, 10, 50, 99])
    out, ref = _sds_and_reference(setup, 7.5, t)
    torch.testing.assert_close(x.grad.double(), ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out.grad.double(), ref, rtol=1e-5, atol=1e-6)
    # loss value is 0.5 ||g||^2 and the prior's weights got no gradient
    assert abs(float(out.loss.detach()) - 0.5 * float((ref ** 2).sum())) < 1e-3 * float((ref ** 2).sum())
    assert prior.a.grad is None
    torch.testing.assert_close(out.w, 1 - prior.alphas_cumprod[t])


def test_one_batched_call_with_cond_and_uncond(setup):
    prior, x, emb, g = setup
    sds_loss(prior, x, emb, guidance_scale=3.0, generator=g)
    assert prior.calls == [2 * x.shape[0]]


def test_guidance_scale_zero_is_unconditional_and_one_is_conditional(setup):
    prior, x, emb, _ = setup
    t = torch.full((4,), 30)
    x_t = x.detach()
    for scale, which in ((0.0, emb.uncond), (1.0, emb.cond)):
        eps = guided_noise(prior, x_t, t, emb, scale)
        direct = prior.predict_noise(x_t, t, which.expand(4, 3))
        torch.testing.assert_close(eps, direct)


def test_huge_guidance_scale_stays_finite_and_exact(setup):
    _, x, _, _ = setup
    out, ref = _sds_and_reference(setup, 1e6, torch.tensor([1, 20, 60, 99]))     # ref ~1e6 (cond - uncond) w(t)
    assert out.finite and torch.isfinite(out.loss) and torch.isfinite(x.grad).all()
    assert float(ref.abs().max()) > 1e5
    torch.testing.assert_close(x.grad.double(), ref, rtol=1e-5, atol=1e-6 * float(ref.abs().max()))
    assert out.grad_norm > 1e5


@pytest.mark.parametrize("schedule", ["linear", "cosine"])
def test_extreme_timesteps_are_finite(schedule):
    prior = FakePrior(T=1000).freeze()
    prior.alphas_cumprod = alphas_cumprod(1000, schedule)
    emb = prior.embed_prompt("x")
    x = torch.randn(2, 3, 8, 8).requires_grad_(True)
    out = sds_loss(prior, x, emb, guidance_scale=100.0, t=torch.tensor([0, 999]))
    out.loss.backward()
    assert torch.isfinite(out.loss) and torch.isfinite(x.grad).all()
    assert 0.0 <= float(out.w[0]) < 1e-3 and float(out.w[1]) > 0.99


def test_timestep_range_defaults_and_bad_fractions():
    assert timestep_range(1000) == (20, 979)
    assert timestep_range(1000, 0.0, 1.0) == (0, 999)
    from l3d_app.errors import UserError
    with pytest.raises(UserError):
        timestep_range(1000, 0.9, 0.1)
    g = torch.Generator().manual_seed(1)
    prior = FakePrior(T=1000).freeze()
    x = torch.zeros(256, 3, 2, 2, requires_grad=True)
    out = sds_loss(prior, x, prior.embed_prompt("x"), t_min=0.5, t_max=0.6, generator=g)
    assert int(out.t.min()) >= 500 and int(out.t.max()) <= 599


def test_nan_prior_is_caught_and_never_applied(setup):
    _, x, emb, g = setup
    bad = FakePrior(nan=True).freeze()
    with pytest.raises(NonFiniteSDSGradient):
        sds_loss(bad, x, emb, generator=g)
    out = SDSLoss(on_nonfinite="flag")(bad, x, emb, g)
    assert not out.finite and torch.isnan(out.loss) and not out.loss.requires_grad
    assert x.grad is None


def test_nan_prior_step_is_skipped_by_training_loop(setup, tmp_path):
    from l3d_app.runtime.context import RunContext
    from l3d_app.runtime.logger import RunLogger
    from l3d_app.runtime.training import LoopSpec, Trainable, train
    _, _, emb, g = setup
    bad = FakePrior(nan=True).freeze()
    image = torch.nn.ParameterDict({"x": torch.nn.Parameter(torch.zeros(1, 3, 8, 8))})
    before = image["x"].detach().clone()
    ctx = RunContext(out_dir=tmp_path, device=torch.device("cpu"), generator=g,
                     logger=RunLogger(tmp_path, enabled=False))
    loss = SDSLoss(on_nonfinite="flag")
    result = train(ctx, Trainable({"image": image}, torch.optim.Adam(image.parameters(), lr=0.1)), lambda i: {"loss": loss(bad, image["x"], emb, g).loss}, LoopSpec(3))
    assert result.skipped_steps == 3
    torch.testing.assert_close(image["x"].detach(), before)


def test_rgb_to_model_space_resizes_and_keeps_gradient():
    prior = FakePrior(size=8)
    rgb = torch.rand(2, 16, 16, 3, requires_grad=True)
    z = rgb_to_model_space(prior, rgb, channels_last=True)
    assert z.shape == (2, 3, 8, 8) and float(z.detach().min()) >= -1 and float(z.detach().max()) <= 1
    z.sum().backward()
    assert torch.isfinite(rgb.grad).all() and float(rgb.grad.abs().sum()) > 0
