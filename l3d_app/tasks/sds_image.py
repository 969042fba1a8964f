"""sds_image: optimise one image (pixel space) or latent (latent space) from a prompt by SDS.

The variable ``x`` (1, *latent_shape) lives in the prior's model space: pixels in [-1, 1]
(``space=pixel``, clamped to that range after each step) or latents (``space=latent``,
decoded by the prior's decoder). It starts at the encoding of a flat grey image plus
``init_noise`` Gaussian noise. Each step averages the SDS gradient
(:func:`l3d_app.losses.sds.sds_loss`: t in [t_min, t_max], w(t) = 1 - abar_t, CFG scale
``guidance_scale``; with ``t_max_end`` set (default 0.5), t_max falls linearly to it over
the run) over ``batch`` draws of (t, noise) and takes an Adam step (in pixel space the
image is first rolled by a random offset of up to ``shift`` pixels, which keeps the prior's
2 x 2 patch grid from printing a checkerboard); a non-finite gradient is never applied (the
shared loop skips the step and counts it).

Course variants (measured in docs/course_exercises.md): ``sds_target=pixel`` (latent priors:
the decoded current and target latents are compared in RGB, see :mod:`l3d_app.losses.sds`),
``lr_warmup`` / ``lr_final_ratio`` (linear warm-up over ``lr_warmup`` steps, then half a cosine
down to ``lr_final_ratio * lr`` at the last step, :func:`l3d_app.runtime.lr_schedules.warmup_cosine`;
stepped by the shared loop) and ``latent_clip`` (latents clamped to ``[-c, c]`` after each step).

Outputs: ``final.png`` (native size and ``final_x8.png`` enlarged), ``progress.gif``
(decoded image every ``frame_every`` steps), TensorBoard images ``sds/image`` over the
iterations, and ``metrics.json``: the independent checker's verdict
(:mod:`l3d_app.metrics.prompt_match`; ``match`` 1/0 and what it saw), ``seconds``,
``iters``, ``skipped_steps``. The checker only judges prompts in the built-in vocabulary
that name a shape; for other prompts (e.g. with ``prior=stable_diffusion``) ``match`` is
left out.
"""

from __future__ import annotations

from typing import Dict, List

import torch
import torch.nn.functional as F

from l3d_app.data.prompt_images import ANY, parse_prompt
from l3d_app.diffusion.registry import PRIORS
from l3d_app.errors import UserError
from l3d_app.losses.sds import SDSLoss
from l3d_app.metrics.prompt_match import check_image
from l3d_app.registry import TASKS
from l3d_app.runtime.lr_schedules import warmup_cosine
from l3d_app.runtime.media import save_gif, save_png, to_uint8
from l3d_app.runtime.random import randint, randn
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec, require_nonnegative, require_positive


def _in_vocabulary(prompt: str) -> bool:
    """Whether the checker can judge ``prompt`` (it names a shape in the built-in vocabulary)."""
    try:
        return parse_prompt(prompt)[1] != ANY
    except UserError:
        return False


def _hwc(images: torch.Tensor) -> torch.Tensor:
    """(1, 3, H, W) -> (H, W, 3) on the CPU."""
    return images[0].detach().permute(1, 2, 0).float().cpu()


@TASKS.register("sds_image")
def sds_image(cfg, ctx) -> dict:
    """Optimise, log the image over iterations, check the result; return the metrics."""
    require_positive(cfg, "iters", "lr", "batch", "frame_every")
    require_nonnegative(cfg, "shift", "init_noise")     # a roll in pixels, a standard deviation
    if not str(cfg.prompt).strip():
        raise UserError("prompt must not be empty, e.g. prompt='a red circle'")
    prior = PRIORS.build(cfg.prior, device=ctx.device)
    if str(cfg.space) != ("latent" if prior.is_latent else "pixel"):
        raise UserError(f"space={cfg.space} but the prior works in "
                        f"{'latent' if prior.is_latent else 'pixel'} space")
    emb = prior.embed_prompt(str(cfg.prompt))
    S = int(prior.image_size)
    with torch.no_grad():
        grey = torch.full((1, 3, S, S), 0.5, device=ctx.device)
        x0 = prior.encode(grey).float()
        x0 = x0 + float(cfg.init_noise) * randn(x0.shape, ctx.generator, x0.device)
    holder = torch.nn.ParameterDict({"x": torch.nn.Parameter(x0)})
    optimizer = torch.optim.Adam(holder.parameters(), lr=float(cfg.lr))
    warmup, final_ratio = int(cfg.get("lr_warmup", 0)), float(cfg.get("lr_final_ratio", 1.0))
    if warmup < 0 or not 0 <= final_ratio <= 1:
        raise UserError(f"need lr_warmup >= 0 and 0 <= lr_final_ratio <= 1, got {warmup}, {final_ratio}")
    schedulers = [] if warmup == 0 and final_ratio == 1.0 else [torch.optim.lr_scheduler.LambdaLR(
        optimizer, warmup_cosine(warmup, warmup, int(cfg.iters), final_ratio))]
    frames: List[torch.Tensor] = []          # uint8 (H, W, 3): checkpointed, so a resumed progress.gif is whole
    trainable = Trainable({"image": holder}, optimizer, extra={"frames": frames}, schedulers=schedulers)
    clip = cfg.get("latent_clip")
    if clip is not None and (not prior.is_latent or not float(clip) > 0):
        raise UserError(f"latent_clip needs a latent prior (space=latent) and a value > 0, got {clip}")
    sds = SDSLoss(float(cfg.guidance_scale), float(cfg.t_min), float(cfg.t_max), str(cfg.weighting),
                  on_nonfinite="flag", target_space=str(cfg.get("sds_target", "model")))
    B = int(cfg.batch)
    t_top = float(cfg.t_max)
    t_end = None if cfg.get("t_max_end") is None else float(cfg.t_max_end)
    if t_end is not None and not float(cfg.t_min) <= t_end <= t_top:
        raise UserError(f"need t_min <= t_max_end <= t_max, got t_max_end={t_end}")
    last: Dict[str, float] = {}

    def decode() -> torch.Tensor:
        with torch.no_grad():
            return prior.decode(holder["x"].detach()).float().clamp(0, 1)

    shift = int(cfg.shift) if not prior.is_latent else 0

    def step(i: int) -> Dict[str, torch.Tensor]:
        x = holder["x"].expand(B, *holder["x"].shape[1:])
        if shift > 0:  # random roll: the prior's patch grid never lines up with the same pixels
            dy, dx = randint(-shift, shift + 1, (2,), ctx.generator).tolist()
            x = torch.roll(x, (dy, dx), dims=(2, 3))
        if t_end is not None:  # anneal the top of the t range linearly: coarse first, details last
            sds.t_max = t_top + (t_end - t_top) * i / max(1, int(cfg.iters) - 1)
        out = sds(prior, x, emb, ctx.generator)
        last.update(grad_norm=out.grad_norm, t=float(out.t.float().mean()))
        return {"loss": out.loss / B, "grad_norm": torch.tensor(out.grad_norm),
                "t": out.t.float().mean()}

    def after(i: int) -> None:
        if not prior.is_latent:
            with torch.no_grad():
                holder["x"].clamp_(-1, 1)
        elif clip is not None:
            with torch.no_grad():
                holder["x"].clamp_(-float(clip), float(clip))
        if i % int(cfg.frame_every) == 0 or i == int(cfg.iters) - 1:
            img = decode()
            frames.append(torch.from_numpy(to_uint8(_hwc(img))))
            ctx.logger.image("sds/image", _hwc(img), i)

    with ctx.stopwatch.stage("optimise"):
        result = train(ctx, trainable, step, loop_spec(cfg, "sds_image"), after_step=after)
    final = decode()
    save_png(ctx.path("final.png"), _hwc(final))
    big = F.interpolate(final, scale_factor=8, mode="nearest")
    save_png(ctx.path("final_x8.png"), _hwc(big))
    if frames:
        big_frames = F.interpolate(torch.stack(frames).float().div(255.0).permute(0, 3, 1, 2), scale_factor=4,
                                   mode="nearest")
        save_gif(ctx.path("progress.gif"), big_frames.permute(0, 2, 3, 1), fps=float(cfg.fps))
    metrics = {"prompt": str(cfg.prompt), "guidance_scale": float(cfg.guidance_scale), "space": str(cfg.space),
               "sds_target": sds.target_space, "lr_warmup": warmup, "lr_final_ratio": final_ratio,
               "latent_clip": None if clip is None else float(clip),
               "iters": result.step, "skipped_steps": result.skipped_steps,
               "final_grad_norm": round(float(last.get("grad_norm", float("nan"))), 5),
               "optimise_seconds": round(ctx.stopwatch.stages["optimise"], 3)}
    if _in_vocabulary(str(cfg.prompt)):
        verdict = check_image(_hwc(final), str(cfg.prompt))
        ctx.logger.text("sds/verdict", str(verdict.as_dict()))
        metrics.update({"match": int(verdict.match), "seen_colour": verdict.colour, "seen_shape": verdict.shape,
                        "seen_background": verdict.background, "fill_ratio": verdict.fill_ratio,
                        "area_fraction": verdict.area_fraction})
    return metrics
