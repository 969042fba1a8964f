"""The course's SDS variants: pixel-space SDS for a latent prior, LR warm-up + cosine, latent clipping."""

from __future__ import annotations

import json

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.diffusion.registry import PRIORS
from l3d_app.diffusion.schedule import alphas_cumprod
from l3d_app.errors import UserError
from l3d_app.losses.sds import sds_loss
from l3d_app.runtime.lr_schedules import warmup_cosine
from sds_oracles import LatentOracle



class TanhLatentPrior(DiffusionPrior):
    """A latent prior with a known decoder ``D(z) = (tanh(z) + 1) / 2`` and noise ``eps = 0.5 x_t + c``."""

    is_latent = True

    def __init__(self):
        super().__init__()
        self.register_buffer("alphas_cumprod", alphas_cumprod(100, "linear"))
        self.latent_shape, self.image_size = (3, 4, 4), 4

    def embed_prompt(self, prompt):
        return PromptEmbedding(cond=torch.tensor([[1.0, -2.0, 0.5]]), uncond=torch.zeros(1, 3))

    def predict_noise(self, x_t, t, condition):
        return 0.5 * x_t + condition.view(-1, 3, 1, 1)

    def encode(self, images):
        return torch.atanh((images * 2 - 1).clamp(-0.999, 0.999))

    def decode(self, z):
        return (torch.tanh(z) + 1) / 2


def test_pixel_space_sds_gradient_goes_through_the_decoder():
    g = torch.Generator().manual_seed(0)
    prior = TanhLatentPrior()
    x = torch.randn(2, 3, 4, 4, generator=g, dtype=torch.float32).requires_grad_(True)
    t, noise = torch.tensor([10, 70]), torch.randn(2, 3, 4, 4, generator=g)
    emb = prior.embed_prompt("x")
    model = sds_loss(prior, x, emb, 3.0, t=t, noise=noise)
    (gz,) = torch.autograd.grad(model.loss, x)
    torch.testing.assert_close(gz, model.grad)                      # latent SDS: the gradient is g
    pixel = sds_loss(prior, x, emb, 3.0, t=t, noise=noise, target_space="pixel")
    (gp,) = torch.autograd.grad(pixel.loss, x)
    # d/dz 0.5 |D(z) - D(z - g)|^2 = D'(z) (D(z) - D(z - g)), D'(z) = (1 - tanh^2 z) / 2
    z, gd = x.detach().double(), model.grad.double()
    expected = 0.5 * (1 - torch.tanh(z) ** 2) * 0.5 * (torch.tanh(z) - torch.tanh(z - gd))
    torch.testing.assert_close(gp.double(), expected, rtol=1e-4, atol=1e-6)
    assert torch.isfinite(gp).all()


def test_pixel_space_sds_needs_a_latent_prior():
    class PixelPrior(TanhLatentPrior):
        is_latent = False

    x = torch.zeros(1, 3, 4, 4, requires_grad=True)
    with pytest.raises(UserError, match="latent prior"):
        sds_loss(PixelPrior(), x, PixelPrior().embed_prompt("x"), target_space="pixel")
    with pytest.raises(UserError, match="target space"):
        sds_loss(TanhLatentPrior(), x, TanhLatentPrior().embed_prompt("x"), target_space="rgb")


if "sds_test_latent_oracle" not in PRIORS:
    PRIORS.register("sds_test_latent_oracle")(LatentOracle)


def _run(compose, out, *overrides):
    cfg = compose("task=sds_image", "threads=1", "tensorboard=false", "frame_every=5", "space=latent",
                  "prior.name=sds_test_latent_oracle", "prompt='a blue square on black'", *overrides)
    run_task(cfg, out)
    return json.loads((out / "metrics.json").read_text()), torch.load(out / "checkpoint.pt", weights_only=False)


@pytest.mark.parametrize("target", ["model", "pixel"])
def test_both_targets_reach_the_oracle_latent(compose, tmp_path, target):
    m, _ = _run(compose, tmp_path, f"sds_target={target}", "iters=150", "lr=0.05", "guidance_scale=1.0",
                "t_max=0.5")
    assert m["match"] == 1 and m["sds_target"] == target


def test_lr_schedule_and_latent_clip(compose, tmp_path):
    # guidance 3 pulls the latent towards 3 x (the image's latent in [-1, 1]): beyond a clip of 1.5
    free, ck_free = _run(compose, tmp_path / "free", "iters=40", "lr=0.1", "guidance_scale=3.0")
    clip, ck_clip = _run(compose, tmp_path / "clip", "iters=40", "lr=0.1", "guidance_scale=3.0",
                         "latent_clip=1.5", "lr_warmup=5", "lr_final_ratio=0.1")
    assert float(ck_free["trainable"]["modules"]["image"]["x"].abs().max()) > 1.6
    assert float(ck_clip["trainable"]["modules"]["image"]["x"].abs().max()) <= 1.5 + 1e-6
    group = ck_clip["trainable"]["optimizer"]["param_groups"][0]
    assert group["lr"] == pytest.approx(0.1 * warmup_cosine(5, 5, 40, 0.1)(40))   # stepped by the loop: 0.01
    assert ck_free["trainable"]["optimizer"]["param_groups"][0]["lr"] == 0.1
    assert clip["latent_clip"] == 1.5 and clip["lr_warmup"] == 5
    with pytest.raises(UserError, match="latent_clip"):
        _run(compose, tmp_path / "bad", "iters=2", "latent_clip=-1")
