"""The interface every diffusion prior offers to score distillation (SDS).

A prior works in its own *model space*: pixels in [-1, 1] for a pixel-space prior, VAE
latents for a latent prior. Images handed to :meth:`DiffusionPrior.encode` are always RGB
in [0, 1], shape (B, 3, H, W); :meth:`decode` returns the same. Timesteps are integer
indices into :attr:`alphas_cumprod` (0 = almost clean, T - 1 = almost pure noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class PromptEmbedding:
    """Conditional and unconditional embeddings of one prompt.

    ``cond`` and ``uncond`` have the prior's own shape per sample (e.g. (1, 77, 768) for
    Stable Diffusion, (1, D) for the built-in prior); the leading dimension is 1 and is
    expanded to the batch by :meth:`DiffusionPrior.predict_noise` callers.
    """

    cond: torch.Tensor
    uncond: torch.Tensor


class DiffusionPrior(torch.nn.Module):
    """Abstract noise-prediction prior (epsilon parameterisation).

    Subclasses set ``alphas_cumprod`` (float32 buffer of shape (T,), decreasing in (0, 1)),
    ``latent_shape`` ((C, h, w) of the model space for the prior's native image size),
    ``image_size`` (native pixel side) and ``is_latent`` and implement the methods below.
    Parameters are frozen by :meth:`freeze`; SDS never trains the prior.
    """

    alphas_cumprod: torch.Tensor
    latent_shape: tuple[int, int, int]
    image_size: int
    is_latent: bool = False

    @property
    def num_timesteps(self) -> int:
        return int(self.alphas_cumprod.shape[0])

    def embed_prompt(self, prompt: str) -> PromptEmbedding:
        """Embeddings of ``prompt`` and of the empty prompt (for classifier-free guidance)."""
        raise NotImplementedError

    def predict_noise(self, x_t: torch.Tensor, t: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        """Predicted noise eps(x_t, t, c).

        x_t: (B, *latent_shape) noisy model-space sample; t: (B,) long timesteps;
        condition: (B, ...) embeddings (``cond`` or ``uncond`` expanded). Returns (B, *latent_shape).
        """
        raise NotImplementedError

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """RGB (B, 3, H, W) in [0, 1] -> model space (B, *latent_shape)."""
        raise NotImplementedError

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Model space (B, *latent_shape) -> RGB (B, 3, H, W) in [0, 1]."""
        raise NotImplementedError

    def freeze(self) -> "DiffusionPrior":
        """Eval mode, no gradients into the prior's weights; returns self."""
        self.eval()
        for p in self.parameters():
            p.requires_grad_(False)
        return self

    def add_noise(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Forward process q(x_t | x_0): sqrt(abar_t) x0 + sqrt(1 - abar_t) noise. Shapes (B, ...)."""
        abar = self.alphas_cumprod.to(x0.device)[t].view(-1, *([1] * (x0.dim() - 1)))
        return abar.sqrt() * x0 + (1 - abar).sqrt() * noise
