"""The built-in prior: a small conditional DDPM trained by the app on procedural prompt images.

``space="pixel"``: the U-Net denoises RGB mapped to [-1, 1] at ``image_size`` (32 by default).
``space="latent"``: it denoises the latents of a tiny autoencoder (4 x 8 x 8 for 32 x 32
images), rescaled to unit standard deviation as Stable Diffusion does with its VAE.

Prompts are parsed into (colour, shape, background) slots
(:func:`l3d_app.prompt_vocab.parse_prompt`); each slot has a learned embedding with an
extra "null" row. The unconditional embedding is all-null; training drops slots at random
(classifier-free-guidance dropout) so partial prompts ("a red circle") are in distribution.

The weights ship as ``l3d_app/assets/builtin_prior.pt`` (see the README there for the
command and seed that made it); ``python main.py task=train_prior`` makes a new one.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Dict, Optional

import torch
import torch.nn as nn

from l3d_app.prompt_vocab import ANY, BACKGROUNDS, COLOURS, SHAPES, parse_prompt
from l3d_app.diffusion.autoencoder import TinyAutoencoder
from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.diffusion.registry import PRIORS
from l3d_app.diffusion.schedule import alphas_cumprod
from l3d_app.diffusion.unet import TinyUNet
from l3d_app.errors import UserError
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.random import rand, randint, randn
from l3d_app.runtime.torch_files import read_torch_file

DEFAULT_CHECKPOINT = Path(__file__).resolve().parents[1] / "assets" / "builtin_prior.pt"
FORMAT = "l3d_builtin_prior/1"
SPACES = ("pixel", "latent")
SLOT_SIZES = (len(COLOURS), len(SHAPES), len(BACKGROUNDS))


class SlotEmbedding(nn.Module):
    """(B, 3) slot indices (ANY = -1 for null) -> (B, 3 * dim) concatenated embeddings."""

    def __init__(self, dim: int = 16):
        super().__init__()
        self.tables = nn.ModuleList([nn.Embedding(n + 1, dim) for n in SLOT_SIZES])

    def forward(self, labels: torch.Tensor) -> torch.Tensor:
        out = []
        for k, (table, n) in enumerate(zip(self.tables, SLOT_SIZES)):
            idx = labels[:, k]
            out.append(table(torch.where(idx == ANY, torch.full_like(idx, n), idx)))
        return torch.cat(out, dim=1)


class BuiltinPrior(DiffusionPrior):
    """Conditional noise predictor over pixels or tiny-autoencoder latents (see module doc)."""

    def __init__(self, space: str = "pixel", image_size: int = 32, channels: int = 32,
                 latent_channels: int = 4, slot_dim: int = 16, num_timesteps: int = 1000,
                 schedule: str = "cosine", patch: int = 2, prediction: str = "v"):
        super().__init__()
        if space not in SPACES:
            raise UserError(f"unknown prior space '{space}' (known: {', '.join(SPACES)})")
        if prediction not in ("eps", "v"):
            raise UserError(f"prediction must be 'eps' or 'v', got '{prediction}'")
        if int(image_size) % 16:
            raise UserError(f"the built-in prior needs image_size divisible by 16, got {image_size}")
        self.config = dict(space=space, image_size=int(image_size), channels=int(channels),
                           latent_channels=int(latent_channels), slot_dim=int(slot_dim),
                           num_timesteps=int(num_timesteps), schedule=schedule,
                           patch=int(patch), prediction=prediction)
        self.is_latent = space == "latent"
        self.image_size = int(image_size)
        self.slots = SlotEmbedding(slot_dim)
        c = latent_channels if self.is_latent else 3
        self.unet = TinyUNet(c, channels, cond_dim=3 * slot_dim, patch=1 if self.is_latent else patch)
        self.autoencoder = TinyAutoencoder(latent_channels) if self.is_latent else None
        side = self.image_size // 4 if self.is_latent else self.image_size
        self.latent_shape = (c, side, side)
        self.register_buffer("alphas_cumprod", alphas_cumprod(num_timesteps, schedule))
        self.register_buffer("latent_scale", torch.ones(()))

    def embed_labels(self, labels: torch.Tensor) -> torch.Tensor:
        """(B, 3) slot indices -> (B, 3 * slot_dim) condition vectors."""
        return self.slots(labels.to(self.alphas_cumprod.device))

    def embed_prompt(self, prompt: str) -> PromptEmbedding:
        device = self.alphas_cumprod.device
        cond = torch.tensor([parse_prompt(prompt)], device=device)
        uncond = torch.full((1, 3), ANY, device=device)
        return PromptEmbedding(cond=self.embed_labels(cond), uncond=self.embed_labels(uncond))

    def _abar(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return self.alphas_cumprod[t].view(-1, *([1] * (like.dim() - 1))).to(like.dtype)

    def predict_noise(self, x_t: torch.Tensor, t: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        """eps from the U-Net's output; with v-prediction eps = sqrt(1 - abar) x_t + sqrt(abar) v."""
        out = self.unet(x_t, t, condition)
        if self.config["prediction"] == "eps":
            return out
        abar = self._abar(t, x_t)
        return (1 - abar).sqrt() * x_t + abar.sqrt() * out

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        if self.autoencoder is None:
            return images * 2 - 1
        return self.autoencoder.encode(images) * self.latent_scale

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        if self.autoencoder is None:
            return ((z + 1) / 2).clamp(0, 1)
        return self.autoencoder.decode(z / self.latent_scale)

    def diffusion_loss(self, images: torch.Tensor, labels: torch.Tensor, generator: torch.Generator,
                       slot_drop: float = 0.2, all_drop: float = 0.1) -> torch.Tensor:
        """DDPM MSE on clean images (B, 3, S, S) with CFG dropout of label slots.

        The target is the noise (``prediction="eps"``) or v = sqrt(abar) eps - sqrt(1 - abar) x0
        (``"v"``, which weights the clean-image error by SNR + 1 and learns faster here).
        """
        B = images.shape[0]
        dev = images.device
        with torch.no_grad():
            x0 = self.encode(images)
        drop = rand((B, 3), generator, dev) < slot_drop
        drop |= rand((B, 1), generator, dev) < all_drop
        labels = torch.where(drop, torch.full_like(labels, ANY), labels)
        t = randint(0, self.num_timesteps, (B,), generator, dev)
        noise = randn(x0.shape, generator, dev)
        out = self.unet(self.add_noise(x0, t, noise), t, self.embed_labels(labels))
        if self.config["prediction"] == "eps":
            target = noise
        else:
            abar = self._abar(t, x0)
            target = abar.sqrt() * noise - (1 - abar).sqrt() * x0
        return ((out - target) ** 2).mean()


def export_state(priors: Dict[str, BuiltinPrior], meta: Dict[str, Any]) -> Dict[str, Any]:
    """A compact (float16) checkpoint of one or both spaces, each with provenance ``meta``."""
    return {"format": FORMAT,
            "spaces": {space: {"config": p.config, "meta": dict(meta),
                               "state": {k: (v.half() if v.is_floating_point() and k != "alphas_cumprod" else v)
                                         for k, v in p.state_dict().items()}}
                       for space, p in priors.items()}}


def save_prior_checkpoint(path: os.PathLike, state: Dict[str, Any], merge: bool = False) -> None:
    """Write ``state`` (from :func:`export_state`) atomically; with ``merge`` the spaces that
    ``state`` lacks are kept from an existing checkpoint at ``path``."""
    path = Path(path)
    if merge and path.exists():
        old = torch.load(path, map_location="cpu", weights_only=True)
        if isinstance(old, dict) and old.get("format") == FORMAT:
            state = {"format": FORMAT, "spaces": {**old["spaces"], **state["spaces"]}}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_builtin_prior(space: str = "pixel", checkpoint: Optional[os.PathLike] = None,
                       device="cpu") -> BuiltinPrior:
    """The frozen built-in prior of ``space`` from ``checkpoint`` (default: the shipped asset)."""
    path = resolve_path(checkpoint) if checkpoint else DEFAULT_CHECKPOINT
    if not path.exists():
        raise UserError(f"built-in prior checkpoint not found: {path} (make one with "
                        f"`python main.py task=train_prior` and pass prior.checkpoint=<run dir>/builtin_prior.pt)")
    state = read_torch_file(path, "built-in prior checkpoint", weights_only=True)
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise UserError(f"{path} is not a built-in prior checkpoint (format {FORMAT})")
    if space not in state["spaces"]:
        raise UserError(f"{path} holds no '{space}' prior (it has: {', '.join(state['spaces'])})")
    entry = state["spaces"][space]
    prior = BuiltinPrior(**entry["config"])
    prior.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in entry["state"].items()})
    return prior.to(device).freeze()


@PRIORS.register("builtin")
def builtin_prior(space: str = "pixel", checkpoint: Optional[str] = None, device="cpu") -> BuiltinPrior:
    """Registry entry for ``conf/prior/builtin.yaml``."""
    return load_builtin_prior(space, checkpoint, device)
