"""Classifier-free guidance: the guided noise prediction of a prior (used by sampling and SDS)."""

from __future__ import annotations

import torch

from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding


def guided_noise(prior: DiffusionPrior, x_t: torch.Tensor, t: torch.Tensor,
                 embedding: PromptEmbedding, guidance_scale: float) -> torch.Tensor:
    """Classifier-free-guided noise ``eps_u + s (eps_c - eps_u)`` from ONE batched call.

    x_t: (B, *latent_shape); t: (B,) long; the embedding's leading dimension is 1 (one
    prompt for the batch) or B (one prompt per sample). Returns float32 (B, *latent_shape).
    """
    B = x_t.shape[0]
    cond = embedding.cond.to(x_t.device)
    uncond = embedding.uncond.to(x_t.device)
    cond = cond.expand(B, *cond.shape[1:])
    uncond = uncond.expand(B, *uncond.shape[1:])
    eps = prior.predict_noise(torch.cat([x_t, x_t]), torch.cat([t, t]), torch.cat([cond, uncond]))
    eps_c, eps_u = eps.float().chunk(2)
    return eps_u + float(guidance_scale) * (eps_c - eps_u)
