"""Score distillation sampling (SDS, DreamFusion): a diffusion prior's gradient as a loss.

For a model-space sample ``x`` (pixels in [-1, 1] or VAE latents, see
:mod:`l3d_app.diffusion.prior`), one SDS step draws ``t ~ U{t_lo..t_hi}`` and
``eps ~ N(0, I)``, forms ``x_t = sqrt(abar_t) x + sqrt(1 - abar_t) eps`` and asks the
prior for the classifier-free-guided noise

    eps_hat = eps_u + s (eps_c - eps_u)            (one batched call: cond and uncond)

The SDS gradient ``g = w(t) (eps_hat - eps)`` (no Jacobian through the prior) is applied
with the *target trick*: ``loss = 0.5 * sum((x - sg(x - g))^2)`` whose gradient w.r.t. ``x``
is exactly ``g`` (summed over the batch and all elements, so every sample receives its own
``g`` unscaled). The loss *value* equals ``0.5 ||g||^2``; it is a diagnostic, not an
objective that decreases.

Pixel-space SDS for a latent prior (``target_space="pixel"``, the course's variant): the same
``g`` defines the target latent ``sg(z - g)``; both the current and the target latent are
decoded and the loss is ``0.5 * sum((D(z) - sg(D(z - g)))^2)`` in RGB, so the gradient on
``z`` is ``J_D^T (D(z) - D(z - g))`` (through the decoder's Jacobian) instead of ``g``.

A non-finite ``g`` (a prior returning NaN/Inf) is never applied: by default it raises
:class:`NonFiniteSDSGradient`; with ``on_nonfinite="flag"`` the returned loss is a NaN
constant without a graph (the shared training loop then skips the step) and
``SDSOutput.finite`` is False.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import torch
import torch.nn.functional as F

from l3d_app.diffusion.guidance import guided_noise  # noqa: F401  (re-exported: older imports)
from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.errors import UserError
from l3d_app.runtime.random import randint, randn

WEIGHTINGS = ("sds", "uniform")  # w(t) = 1 - abar_t (DreamFusion) | w(t) = 1
TARGET_SPACES = ("model", "pixel")  # the loss on the model-space sample | on its decoded RGB (latent priors)


class NonFiniteSDSGradient(FloatingPointError):
    """The prior produced a non-finite SDS gradient; nothing was applied."""


@dataclass
class SDSOutput:
    """One SDS evaluation.

    loss: scalar whose gradient w.r.t. ``x`` is ``grad`` (NaN constant if not finite);
    t: (B,) long timesteps used; w: (B,) weights w(t); grad: (B, *latent_shape) detached
    SDS gradient (zeros where not finite); grad_norm: mean over the batch of ||g_b||_2
    (NaN when not finite); finite: whether ``grad`` was finite everywhere.
    """

    loss: torch.Tensor
    t: torch.Tensor
    w: torch.Tensor
    grad: torch.Tensor
    grad_norm: float
    finite: bool


def timestep_range(num_timesteps: int, t_min: float = 0.02, t_max: float = 0.98) -> Tuple[int, int]:
    """Inclusive integer range [lo, hi] of timesteps for fractions ``t_min <= t_max`` in [0, 1]."""
    if not (0.0 <= float(t_min) <= float(t_max) <= 1.0):
        raise UserError(f"need 0 <= t_min <= t_max <= 1, got t_min={t_min}, t_max={t_max}")
    T = int(num_timesteps)
    lo = min(T - 1, max(0, int(round(float(t_min) * (T - 1)))))
    hi = min(T - 1, max(lo, int(round(float(t_max) * (T - 1)))))
    return lo, hi


def sds_weight(alphas_cumprod: torch.Tensor, t: torch.Tensor, weighting: str = "sds") -> torch.Tensor:
    """w(t) of shape (B,): ``1 - abar_t`` ("sds") or ones ("uniform")."""
    if weighting == "sds":
        return 1.0 - alphas_cumprod.to(t.device)[t].float()
    if weighting == "uniform":
        return torch.ones(t.shape, device=t.device)
    raise UserError(f"unknown SDS weighting '{weighting}' (known: {', '.join(WEIGHTINGS)})")


def sds_loss(prior: DiffusionPrior, x: torch.Tensor, embedding: PromptEmbedding,
             guidance_scale: float = 7.5, t_min: float = 0.02, t_max: float = 0.98,
             weighting: str = "sds", generator: Optional[torch.Generator] = None,
             t: Optional[torch.Tensor] = None, noise: Optional[torch.Tensor] = None,
             on_nonfinite: str = "raise", target_space: str = "model") -> SDSOutput:
    """SDS loss of model-space ``x`` (B, *latent_shape), requiring grad, under ``prompt``.

    ``t``/``noise`` may be given (tests); otherwise drawn from ``generator`` (on x's device).
    The prior runs without gradients; only ``x`` gets one. ``target_space="pixel"`` (latent
    priors only) compares the decoded current and target latents in RGB (module docstring).
    """
    if on_nonfinite not in ("raise", "flag"):
        raise UserError(f"on_nonfinite must be 'raise' or 'flag', got '{on_nonfinite}'")
    if target_space not in TARGET_SPACES:
        raise UserError(f"unknown SDS target space '{target_space}' (known: {', '.join(TARGET_SPACES)})")
    if target_space == "pixel" and not prior.is_latent:
        raise UserError("pixel-space SDS decodes latents: it needs a latent prior (space=latent)")
    B = x.shape[0]
    device = x.device
    if t is None:
        lo, hi = timestep_range(prior.num_timesteps, t_min, t_max)
        t = randint(lo, hi + 1, (B,), generator, device)
    t = t.to(device=device, dtype=torch.long)
    if noise is None:
        noise = randn(x.shape, generator, device)
    x0 = x.detach().float()
    noise = noise.to(device=device, dtype=torch.float32)
    with torch.no_grad():
        x_t = prior.add_noise(x0, t, noise)
        model_dtype = next((p.dtype for p in prior.parameters()), torch.float32)
        eps_hat = guided_noise(prior, x_t.to(model_dtype), t, embedding, guidance_scale)
        w = sds_weight(prior.alphas_cumprod, t, weighting)
        grad = w.view(-1, *([1] * (x.dim() - 1))) * (eps_hat - noise)
        finite = bool(torch.isfinite(grad).all())
    if not finite:
        bad = int((~torch.isfinite(grad)).flatten(1).any(1).sum())
        msg = (f"non-finite SDS gradient in {bad}/{B} samples at t={t.tolist()} "
               f"(guidance_scale={guidance_scale}); not applied")
        if on_nonfinite == "raise":
            raise NonFiniteSDSGradient(msg)
        return SDSOutput(loss=torch.full((), float("nan"), device=device), t=t, w=w,
                         grad=torch.zeros_like(grad), grad_norm=float("nan"), finite=False)
    target = (x0 - grad).to(x.dtype)
    if target_space == "pixel":
        with torch.no_grad():
            target_rgb = prior.decode(target.to(model_dtype)).float()
        loss = 0.5 * F.mse_loss(prior.decode(x.to(model_dtype)).float(), target_rgb, reduction="sum")
    else:
        loss = 0.5 * F.mse_loss(x, target, reduction="sum")
    grad_norm = float(grad.flatten(1).norm(dim=1).mean())
    return SDSOutput(loss=loss, t=t, w=w, grad=grad, grad_norm=grad_norm, finite=True)


class SDSLoss:
    """SDS with fixed settings: ``SDSLoss(guidance_scale=...)(prior, x, embedding, generator)``."""

    def __init__(self, guidance_scale: float = 7.5, t_min: float = 0.02, t_max: float = 0.98,
                 weighting: str = "sds", on_nonfinite: str = "raise", target_space: str = "model"):
        timestep_range(1000, t_min, t_max)  # validates the fractions early
        if target_space not in TARGET_SPACES:
            raise UserError(f"unknown SDS target space '{target_space}' (known: {', '.join(TARGET_SPACES)})")
        self.target_space = target_space
        if weighting not in WEIGHTINGS:
            raise UserError(f"unknown SDS weighting '{weighting}' (known: {', '.join(WEIGHTINGS)})")
        self.guidance_scale, self.t_min, self.t_max = float(guidance_scale), float(t_min), float(t_max)
        self.weighting, self.on_nonfinite = weighting, on_nonfinite

    def __call__(self, prior: DiffusionPrior, x: torch.Tensor, embedding: PromptEmbedding,
                 generator: Optional[torch.Generator] = None) -> SDSOutput:
        return sds_loss(prior, x, embedding, self.guidance_scale, self.t_min, self.t_max,
                        self.weighting, generator, on_nonfinite=self.on_nonfinite,
                        target_space=self.target_space)


def rgb_to_model_space(prior: DiffusionPrior, images: torch.Tensor, channels_last: bool = False,
                       resize: bool = True) -> torch.Tensor:
    """Rendered RGB in [0, 1] -> the prior's model space, differentiably.

    images: (B, 3, H, W), or (B, H, W, 3) with ``channels_last``. With ``resize`` the
    images are bilinearly resized to ``prior.image_size`` first (antialiased when
    shrinking). Returns (B, *latent_shape) via :meth:`DiffusionPrior.encode` (the pixel
    prior maps to [-1, 1]; a latent prior runs its encoder).
    """
    if channels_last:
        images = images.permute(0, 3, 1, 2)
    if images.dim() != 4 or images.shape[1] != 3:
        raise UserError(f"expected RGB images (B, 3, H, W), got shape {tuple(images.shape)}")
    size = int(prior.image_size)
    if resize and tuple(images.shape[-2:]) != (size, size):
        shrink = images.shape[-1] > size or images.shape[-2] > size
        images = F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False,
                               antialias=shrink)
    return prior.encode(images)
