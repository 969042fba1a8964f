"""Deterministic DDIM sampling with classifier-free guidance (to look at / score a prior)."""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.diffusion.guidance import guided_noise
from l3d_app.runtime.random import randn


@torch.no_grad()
def ddim_sample(prior: DiffusionPrior, prompts: Sequence[str], steps: int = 25, guidance_scale: float = 3.0,
                generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """RGB samples (B, 3, S, S) in [0, 1], one per prompt, with ``steps`` DDIM (eta = 0) steps."""
    device = prior.alphas_cumprod.device
    abar = prior.alphas_cumprod.float()
    T = prior.num_timesteps
    B = len(prompts)
    embs = [prior.embed_prompt(p) for p in prompts]
    emb = PromptEmbedding(torch.cat([e.cond for e in embs]), torch.cat([e.uncond for e in embs]))
    x = randn((B, *prior.latent_shape), generator, device)
    times = torch.linspace(T - 1, 0, int(steps), device=device).round().long()
    for i, t in enumerate(times):
        eps = guided_noise(prior, x, t.repeat(B), emb, guidance_scale)
        a_t = abar[t]
        a_prev = abar[times[i + 1]] if i + 1 < len(times) else torch.ones((), device=device)
        x0 = (x - (1 - a_t).sqrt() * eps) / a_t.sqrt()
        x0 = x0.clamp(-1, 1) if not prior.is_latent else x0.clamp(-5, 5)
        x = a_prev.sqrt() * x0 + (1 - a_prev).sqrt() * eps
    return prior.decode(x).clamp(0, 1)

