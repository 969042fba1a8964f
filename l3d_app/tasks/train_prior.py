"""train_prior: train the built-in diffusion prior(s) on procedural prompt images.

Each step draws a fresh batch of ``batch_size`` images of random prompts
(:mod:`l3d_app.data.prompt_images`) and takes one AdamW step on the DDPM v- (or eps-) MSE of
the pixel prior and/or the latent prior (``space`` = pixel | latent | both), with
classifier-free-guidance slot dropout; the learning rate warms up over 100 steps and then
stays (``lr_decay=none``) or falls along a cosine to 5% at the end (``lr_decay=cosine``). The latent prior first trains its autoencoder for
``ae_iters`` steps (reconstruction MSE), fixes the latent scale (1 / std of the latents of
a fixed batch) and then trains its U-Net. Exponential moving averages of the weights
(``ema_decay``) are what gets evaluated and exported.

Evaluation: DDIM samples (``sample_steps`` steps, guidance ``eval_guidance``) of
``eval_prompts`` fully specified prompts per space, scored by the independent checker
(:mod:`l3d_app.metrics.prompt_match`): every ``eval_every`` steps from the VALIDATION noise
(``val_sample_match_<space>``, ``history``), once at the end from the TEST noise
(``sample_match_<space>``; the two noise streams are seeded apart). Runs through the shared training loop (checkpoints, resume,
NaN guard). Outputs: ``builtin_prior.pt`` (float16 weights, loadable with
``prior.checkpoint=<run dir>/builtin_prior.pt``; with ``export=PATH`` also written there,
keeping the other space of an existing checkpoint at PATH), with the command line, seed and
final evaluation recorded inside per space;
``samples_<space>.png``, ``metrics.json``.
"""

from __future__ import annotations

import copy
import sys
from typing import Dict

import torch

from l3d_app.data.prompt_images import prompt_batch
from l3d_app.diffusion.builtin_prior import SPACES, BuiltinPrior, export_state, save_prior_checkpoint
from l3d_app.diffusion.sampling import ddim_sample
from l3d_app.errors import UserError
from l3d_app.metrics.prompt_match import match_rate
from l3d_app.prompt_vocab import full_prompts
from l3d_app.registry import TASKS
from l3d_app.render.charts import image_grid
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.lr_schedules import warmup_cosine
from l3d_app.runtime.media import save_png
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.random import held_out_seed
from l3d_app.runtime.training import Trainable, log_test, train
from l3d_app.tasks.common import loop_spec, require_fraction, require_positive


def _spaces(space: str):
    if space == "both":
        return list(SPACES)
    if space not in SPACES:
        raise UserError(f"space must be pixel, latent or both, got '{space}'")
    return [space]


@torch.no_grad()
def _ema_update(ema: torch.nn.Module, live: torch.nn.Module, decay: float) -> None:
    for e, p in zip(ema.parameters(), live.parameters()):
        e.lerp_(p, 1.0 - decay)
    for e, b in zip(ema.buffers(), live.buffers()):
        e.copy_(b)


def _lr_factor(decay: str, iters: int, ae_iters: int, warmup: int, final: float):
    """lr multiplier of step i: ``warmup``-step warm-up, then constant (``none``) or a cosine
    fall to ``final`` x lr at the last step (``cosine``); the latent U-Net's schedule starts
    after ``ae_iters``."""
    if decay not in ("none", "cosine"):
        raise UserError(f"lr_decay must be 'none' or 'cosine', got '{decay}'")
    return warmup_cosine(int(warmup), ae_iters, iters - 1, float(final) if decay == "cosine" else 1.0)


@TASKS.register("train_prior")
def train_prior(cfg, ctx) -> dict:
    """Train, evaluate sample match rates, export the float16 checkpoint; return metrics."""
    require_positive(cfg, "iters", "batch_size", "lr", "image_size", "channels", "eval_prompts", "sample_steps")
    require_fraction(cfg, "ema_decay", "slot_drop", "all_drop")
    spaces = _spaces(str(cfg.space))
    S, dev, gen = int(cfg.image_size), ctx.device, ctx.generator
    ae_iters = int(cfg.ae_iters) if "latent" in spaces else 0
    if ae_iters >= int(cfg.iters):
        raise UserError(f"ae_iters ({ae_iters}) must be smaller than iters ({cfg.iters})")
    arch = dict(image_size=S, channels=int(cfg.channels), num_timesteps=int(cfg.num_timesteps),
                schedule=str(cfg.schedule), patch=int(cfg.patch), prediction=str(cfg.prediction))
    live = {s: BuiltinPrior(s, **arch).to(dev) for s in spaces}
    ema = {s: copy.deepcopy(m).requires_grad_(False) for s, m in live.items()}
    params = [p for m in live.values() for p in m.parameters()]
    opt = torch.optim.AdamW(params, lr=float(cfg.lr), weight_decay=0.0)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _lr_factor(str(cfg.lr_decay), int(cfg.iters), ae_iters,
                                                          int(cfg.warmup_steps), float(cfg.lr_final_fraction)))
    modules = {**live, **{f"{s}_ema": m for s, m in ema.items()}}
    trainable = Trainable(modules, opt, schedulers=[sched])
    prompts = full_prompts(max(1, int(cfg.eval_prompts) // 3))

    def step(i: int) -> Dict[str, torch.Tensor]:
        images, labels = prompt_batch(int(cfg.batch_size), S, gen, dev)
        logs, total = {}, 0.0
        if "pixel" in live:
            logs["pixel"] = live["pixel"].diffusion_loss(images, labels, gen, float(cfg.slot_drop), float(cfg.all_drop))
            total = total + logs["pixel"]
        if "latent" in live:
            lat = live["latent"]
            if i < ae_iters:
                logs["ae"] = lat.autoencoder.loss(images)
            else:
                if i == ae_iters or float(lat.latent_scale) == 1.0:
                    with torch.no_grad():
                        ref_gen = torch.Generator("cpu").manual_seed(int(cfg.latent_scale_seed))
                        ref, _ = prompt_batch(int(cfg.latent_scale_batch), S, ref_gen, dev)
                        lat.latent_scale.fill_(1.0 / float(lat.autoencoder.encode(ref).std()))
                logs["latent"] = lat.diffusion_loss(images, labels, gen, float(cfg.slot_drop), float(cfg.all_drop))
            total = total + logs.get("ae", 0.0) + logs.get("latent", 0.0)
        logs["loss"] = total
        return logs

    def after(i: int) -> None:
        for s in spaces:
            # the autoencoder is copied, not averaged: the latent U-Net must see the frozen one
            copying = s == "latent" and i < ae_iters + int(cfg.ema_copy_steps)
            _ema_update(ema[s], live[s], 0.0 if copying else float(cfg.ema_decay))

    samples: Dict[str, torch.Tensor] = {}

    def evaluate(_i: int, split: str) -> Dict[str, float]:
        """DDIM samples from the split's own noise (:func:`~l3d_app.runtime.random.held_out_seed`):
        val = seed * 1000 + eval_seed_offset + 1 (every evaluation), test = seed * 1000 +
        eval_seed_offset (once, at the end)."""
        out = {}
        g = torch.Generator("cpu").manual_seed(held_out_seed(int(cfg.seed), int(cfg.eval_seed_offset), split))  # any device
        for s in spaces:
            if s == "latent" and _i <= ae_iters:
                continue
            samples[s] = ddim_sample(ema[s], prompts, int(cfg.sample_steps), float(cfg.eval_guidance), g)
            out[f"sample_match_{s}"] = match_rate(samples[s], prompts)
        return out

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step, loop_spec(cfg, "train_prior"), lambda i: evaluate(i, "val"),
                       TimeBudget.of(ctx).keep_renders(1), after)      # the test samples cost what a validation's do
    test = evaluate(result.step, "test")
    log_test(ctx, test, result.step)
    for s, imgs in samples.items():
        grid = image_grid(imgs, cols=max(1, int(cfg.eval_prompts) // 3))
        save_png(ctx.path(f"samples_{s}.png"), grid)
        ctx.logger.image(f"samples/{s}", grid, result.step)
    meta = {"command": "python main.py " + " ".join(sys.argv[1:]), "seed": int(cfg.seed),
            "iters": result.step, "batch_size": int(cfg.batch_size),
            **{k: round(float(v), 4) for k, v in test.items()}}
    state = export_state({s: ema[s].cpu() for s in spaces}, meta)
    out_path = ctx.path("builtin_prior.pt")
    save_prior_checkpoint(out_path, state)
    if cfg.get("export"):
        save_prior_checkpoint(resolve_path(str(cfg.export)), state, merge=True)
    metrics = {k: round(float(v), 4) for k, v in test.items()}
    metrics.update({
        **result.val_metrics(),
        "history": result.history_rows(),
        "iters": result.step,
        "n_params": sum(p.numel() for m in live.values() for p in m.parameters()),
        "checkpoint_bytes": out_path.stat().st_size,
        "train_seconds": round(result.train_seconds, 3),   # steps only, resumed parts included
        "skipped_steps": result.skipped_steps,
        "interrupted": result.interrupted,
    })
    return metrics
