"""Test support: diffusion priors whose data distribution is ONE image per prompt, so their
noise prediction is exact (the SDS tests' oracles; no network, no weights)."""

from __future__ import annotations

import torch

from l3d_app.data.prompt_images import parse_prompt, render_prompt_images
from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.diffusion.schedule import alphas_cumprod

SIZE = 16


class OraclePrior(DiffusionPrior):
    """A prior whose data distribution is ONE image per condition, so eps is exact:
    eps(x_t, t, c) = (x_t - sqrt(abar) x*_c) / sqrt(1 - abar). Conditional image: the
    procedural image of the prompt; unconditional: flat grey. SDS then pulls x to x*_c
    (guidance scale s: towards x*_u + s (x*_c - x*_u), clamped to [-1, 1] by the task)."""

    is_latent = False

    def __init__(self, **_config):
        super().__init__()
        self.register_buffer("alphas_cumprod", alphas_cumprod(1000, "cosine"))
        self.latent_shape, self.image_size = (3, SIZE, SIZE), SIZE

    def embed_prompt(self, prompt):
        labels = torch.tensor([parse_prompt(prompt)])
        img = render_prompt_images(labels, SIZE, torch.Generator().manual_seed(0), jitter=0.0,
                                   min_radius=0.3, max_radius=0.3, max_offset=0.0)
        return PromptEmbedding(cond=(img * 2 - 1).flatten(1), uncond=torch.zeros(1, 3 * SIZE * SIZE))

    def predict_noise(self, x_t, t, condition):
        a = self.alphas_cumprod[t].view(-1, 1, 1, 1)
        x_star = condition.view(-1, *self.latent_shape)
        return (x_t - a.sqrt() * x_star) / (1 - a).sqrt()

    def encode(self, images):
        return images * 2 - 1

    def decode(self, z):
        return ((z + 1) / 2).clamp(0, 1)


class LatentOracle(OraclePrior):
    """The same oracle as a LATENT prior with the trivial autoencoder ``z = 2 img - 1`` (decode
    not clamped, so a latent outside the image range stays visible)."""

    is_latent = True

    def decode(self, z):
        return (z + 1) / 2
