"""Stable Diffusion as a :class:`~l3d_app.diffusion.prior.DiffusionPrior`, from LOCAL weights only.

``prior=stable_diffusion prior.path=/path/to/weights`` loads a diffusers
``StableDiffusionPipeline`` folder (``model_index.json`` with ``unet/``, ``vae/``,
``text_encoder/``, ``tokenizer/``, ``scheduler/``; e.g. what ``save_pretrained`` writes or a
downloaded snapshot) with ``local_files_only=True`` and the Hugging Face hub switched off
(``HF_HUB_OFFLINE=1``): nothing is ever fetched. The safety checker is not loaded (SDS never
produces final images through the pipeline).

What the prior offers (shapes for SD 1.x at 512 px; the test uses a tiny random pipeline):

* model space: VAE latents ``z = scaling_factor * (mean(q(z | x)) - shift)``, shape
  (B, 4, 64, 64) for (B, 3, 512, 512) RGB in [0, 1] (rescaled to [-1, 1] for the VAE).
  The posterior MEAN is used (deterministic, so the same render always has the same latent).
* ``embed_prompt``: CLIP token ids padded to the tokenizer's ``model_max_length`` (77) ->
  the text encoder's last hidden state (1, 77, 768); ``uncond`` is the empty prompt's.
* ``predict_noise``: the UNet's epsilon prediction, returned as float32.
* ``alphas_cumprod``: the pipeline scheduler's (T = 1000 for SD).

Precision: float16 on CUDA, float32 on the CPU (``dtype=auto``). Inputs are cast to the
weights' dtype inside each call and outputs are float32, so callers never see fp16.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Optional

import torch

from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.diffusion.registry import PRIORS
from l3d_app.errors import UserError
from l3d_app.runtime.paths import resolve_path

INSTALL_HINT = "pip install -e '.[sd]'  (or: pip install diffusers transformers)"
_DTYPES = {"float16": torch.float16, "fp16": torch.float16, "bfloat16": torch.bfloat16,
           "float32": torch.float32, "fp32": torch.float32}


def _offline_diffusers():
    """Import diffusers with every hub access switched off; UserError if not installed."""
    for key in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE"):
        os.environ[key] = "1"
    os.environ.setdefault("HF_HUB_DISABLE_TELEMETRY", "1")
    try:
        import diffusers  # noqa: F401
        import transformers  # noqa: F401
        from diffusers import StableDiffusionPipeline
    except ImportError as err:
        raise UserError(f"prior=stable_diffusion needs diffusers and transformers ({err.name or err} "
                        f"is missing): {INSTALL_HINT}") from None
    try:  # constants are read at import time; cover an earlier import of huggingface_hub
        import huggingface_hub.constants as hub_constants

        hub_constants.HF_HUB_OFFLINE = True
    except (ImportError, AttributeError):
        pass
    return StableDiffusionPipeline


def check_pipeline_folder(path) -> Path:
    """The resolved folder of a diffusers pipeline, or a UserError saying what is wrong."""
    if path is None or not str(path).strip() or str(path).strip() == "???":
        raise UserError("prior=stable_diffusion needs local weights: add prior.path=/path/to/folder "
                        "(a diffusers StableDiffusionPipeline folder with model_index.json)")
    folder = resolve_path(str(path).strip())
    if not folder.exists():
        raise UserError(f"Stable Diffusion weights not found: {folder} does not exist "
                        "(nothing is downloaded; point prior.path at a local pipeline folder)")
    if not folder.is_dir() or not (folder / "model_index.json").is_file():
        raise UserError(f"{folder} is not a diffusers pipeline folder (no model_index.json); "
                        "expected the folder written by StableDiffusionPipeline.save_pretrained "
                        "or a downloaded snapshot with unet/, vae/, text_encoder/, tokenizer/, scheduler/")
    missing = [p for p in ("unet", "vae", "text_encoder", "tokenizer", "scheduler") if not (folder / p).is_dir()]
    if missing:
        raise UserError(f"{folder} lacks the pipeline part(s) {', '.join(missing)}")
    return folder


def resolve_dtype(dtype: str, device: torch.device) -> torch.dtype:
    """'auto' -> float16 on CUDA, float32 elsewhere; else the named dtype (fp16 only on CUDA)."""
    name = str(dtype).lower()
    if name == "auto":
        return torch.float16 if device.type == "cuda" else torch.float32
    if name not in _DTYPES:
        raise UserError(f"unknown prior dtype '{dtype}' (known: auto, {', '.join(sorted(_DTYPES))})")
    return _DTYPES[name]


class StableDiffusionPrior(DiffusionPrior):
    """A latent-space prior around a loaded ``StableDiffusionPipeline`` (see the module docstring).

    Build it with :func:`stable_diffusion_prior` (path checks, offline loading, dtype, device).
    """

    is_latent = True

    def __init__(self, pipe):
        super().__init__()
        self.unet, self.vae, self.text_encoder = pipe.unet, pipe.vae, pipe.text_encoder
        self.tokenizer = pipe.tokenizer
        self.register_buffer("alphas_cumprod",
                             torch.as_tensor(pipe.scheduler.alphas_cumprod).detach().float().clone())
        vae_cfg = self.vae.config
        self.vae_scale = 2 ** (len(vae_cfg.block_out_channels) - 1)
        self.scaling_factor = float(getattr(vae_cfg, "scaling_factor", 0.18215) or 0.18215)
        self.shift_factor = float(getattr(vae_cfg, "shift_factor", None) or 0.0)
        side = int(self.unet.config.sample_size)
        self.latent_shape = (int(self.unet.config.in_channels), side, side)
        self.image_size = side * self.vae_scale
        self.max_length = int(min(self.tokenizer.model_max_length,
                                  self.text_encoder.config.max_position_embeddings))

    @property
    def dtype(self) -> torch.dtype:
        return next(self.unet.parameters()).dtype

    @property
    def device(self) -> torch.device:
        return self.alphas_cumprod.device

    @torch.no_grad()
    def _encode_text(self, prompt: str) -> torch.Tensor:
        ids = self.tokenizer([prompt], padding="max_length", max_length=self.max_length,
                             truncation=True, return_tensors="pt").input_ids.to(self.device)
        return self.text_encoder(ids)[0].float()

    def embed_prompt(self, prompt: str) -> PromptEmbedding:
        """cond / uncond: (1, max_length, hidden) float32 text-encoder states of ``prompt`` / ""."""
        return PromptEmbedding(cond=self._encode_text(str(prompt)), uncond=self._encode_text(""))

    def predict_noise(self, x_t: torch.Tensor, t: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        """x_t (B, 4, h, w), t (B,) long, condition (B, L, D) -> float32 eps (B, 4, h, w)."""
        dt = self.dtype
        out = self.unet(x_t.to(dt), t.to(x_t.device), encoder_hidden_states=condition.to(dt)).sample
        return out.float()

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """RGB (B, 3, H, W) in [0, 1] -> float32 latents (B, 4, H / f, W / f), f = vae_scale.

        Differentiable w.r.t. ``images`` (SDS back-propagates through the encoder).
        """
        x = (images * 2.0 - 1.0).to(self.dtype)
        mean = self.vae.encode(x).latent_dist.mean
        return ((mean - self.shift_factor) * self.scaling_factor).float()

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latents (B, 4, h, w) -> float32 RGB (B, 3, h * f, w * f) in [0, 1]."""
        x = self.vae.decode((z / self.scaling_factor + self.shift_factor).to(self.dtype)).sample
        return ((x.float() + 1.0) / 2.0).clamp(0.0, 1.0)


@PRIORS.register("stable_diffusion")
def stable_diffusion_prior(path: Optional[str] = None, dtype: str = "auto", device=None) -> StableDiffusionPrior:
    """Load a local Stable Diffusion pipeline folder as a frozen prior on ``device``.

    Args:
        path: the pipeline folder (relative paths: working directory, then the repository).
        dtype: auto (float16 on CUDA, float32 on CPU) | float16 | bfloat16 | float32.
        device: torch device (default CPU).
    """
    folder = check_pipeline_folder(path)
    pipeline_cls = _offline_diffusers()
    device = torch.device(device) if device is not None else torch.device("cpu")
    torch_dtype = resolve_dtype(dtype, device)
    try:
        with warnings.catch_warnings():  # diffusers >= 0.36 renames torch_dtype: keep both working
            warnings.simplefilter("ignore", FutureWarning)
            pipe = pipeline_cls.from_pretrained(str(folder), local_files_only=True, torch_dtype=torch_dtype,
                                                safety_checker=None, feature_extractor=None,
                                                requires_safety_checker=False)
    except (OSError, ValueError, KeyError, TypeError, RuntimeError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise UserError(f"could not load a Stable Diffusion pipeline from {folder}: {first}") from None
    return StableDiffusionPrior(pipe).to(device).freeze()
