"""sds_mesh: paint a fixed mesh from a text prompt by score distillation (SDS).

Model: a texture *field*, ``rgb = sigmoid(MLP(harmonic(p)))`` of the surface point ``p``
(world units), so the texture has no UV seams and its resolution does not depend on the
mesh's vertex density. Rendering: the hard rasteriser of ``renderer=mesh`` (visibility is
fixed, the mesh does not move) with the field evaluated at every covered pixel's
interpolated surface point (:class:`FieldTextureRenderer`); shading ``unlit`` (flat colour,
like the built-in prior's images) or ``lambert``/``phong`` with a headlight. Only the
field's parameters are trained; gradients reach them through the per-pixel albedo.

Each step renders ``batch_views`` random cameras on an orbit
(:func:`~l3d_app.diffusion.view_prompts.sample_orbit_cameras`), maps the renders to the
prior's model space and applies :func:`~l3d_app.losses.sds.sds_loss` (CFG, w(t) = 1 -
abar_t, target trick; a non-finite SDS gradient makes the shared loop skip the step).

Measured: every turntable frame (before and after) is scored by the independent prompt
checker (:mod:`l3d_app.metrics.prompt_match`, the built-in prior's vocabulary);
``metrics.json`` has the match rates before/after, per-slot rates, seconds and
seconds per iteration. Outputs: ``sds_mesh.gif`` (turntable, before | after),
``after.png`` (the frames), TensorBoard scalars and the front view over iterations.
"""

from __future__ import annotations

from typing import Dict, Optional

import torch

from l3d_app.data.prompt_images import parse_prompt
from l3d_app.diffusion.registry import PRIORS
from l3d_app.diffusion.view_prompts import sample_orbit_cameras
from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable
from l3d_app.geometry.mesh import Mesh
from l3d_app.losses.sds import rgb_to_model_space, sds_loss
from l3d_app.metrics.prompt_match import check_image
from l3d_app.models.encodings import HarmonicEncoding
from l3d_app.registry import DATASETS, TASKS
from l3d_app.render.mesh_renderer import MeshRenderer
from l3d_app.render.shading import interpolate_vertices
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import render_frames, require_positive


class TextureField(torch.nn.Module):
    """Surface point (N, 3) world units -> RGB (N, 3) in (0, 1).

    ``harmonic(p)`` with ``n_frequencies`` octaves -> ``layers`` ReLU layers of ``hidden``
    -> sigmoid. The output layer starts at zero, so the initial texture is uniform grey 0.5.
    """

    def __init__(self, n_frequencies: int = 4, hidden: int = 64, layers: int = 2):
        super().__init__()
        if hidden < 1 or layers < 1:
            raise UserError(f"texture field needs hidden >= 1 and layers >= 1, got {hidden}, {layers}")
        self.encoding = HarmonicEncoding(3, n_frequencies)
        mods, d = [], self.encoding.out_dim
        for _ in range(int(layers)):
            mods += [torch.nn.Linear(d, hidden), torch.nn.ReLU()]
            d = hidden
        head = torch.nn.Linear(d, 3)
        torch.nn.init.zeros_(head.weight)
        torch.nn.init.zeros_(head.bias)
        self.mlp = torch.nn.Sequential(*mods, head)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.mlp(self.encoding(points)))


class FieldTextureRenderer(MeshRenderer):
    """:class:`MeshRenderer` whose albedo is ``field(surface point)`` at each covered pixel.

    Differentiable w.r.t. the field's parameters (not the geometry or the visibility).
    """

    def __init__(self, field: torch.nn.Module, **kwargs):
        super().__init__(**kwargs)
        self.field = field

    def albedo(self, mesh: Mesh, faces, corners, bary_t: torch.Tensor) -> torch.Tensor:
        points = interpolate_vertices(mesh.verts.t().to(bary_t.dtype), corners, bary_t)  # (3, P)
        return self.field(points.t()).t()


def check_prompt_for_checker(prompt: str):
    """The prompt's (colour, shape, background) slots, or None when the checker cannot read it."""
    try:
        return parse_prompt(prompt)
    except UserError:
        return None


def score_frames(frames: torch.Tensor, prompt: str) -> Dict[str, Optional[float]]:
    """Checker verdicts over frames (N, H, W, 3): match rate and per-slot rates (None if the
    prompt is outside the checker's vocabulary, e.g. a free-text Stable Diffusion prompt)."""
    keys = ("match", "colour_ok", "shape_ok", "background_ok")
    if check_prompt_for_checker(prompt) is None:
        return {k: None for k in keys}
    verdicts = [check_image(f, prompt) for f in frames]
    return {k: sum(bool(getattr(v, k)) for v in verdicts) / max(len(verdicts), 1) for k in keys}


def score_metrics(score: Dict[str, Optional[float]]) -> Dict[str, Optional[float]]:
    """:func:`score_frames` output as metrics.json keys."""
    return {"match_rate": score["match"], "colour_match_rate": score["colour_ok"],
            "shape_match_rate": score["shape_ok"], "background_match_rate": score["background_ok"]}


def load_prior(cfg, device):
    """The configured prior (``prior=builtin`` | ``prior=stable_diffusion prior.path=DIR``), frozen."""
    return PRIORS.build(cfg.prior, device=device)


@TASKS.register("sds_mesh")
def sds_mesh(cfg, ctx) -> dict:
    """Optimise the texture field with SDS; score turntables before and after; write gif/metrics."""
    require_positive(cfg, "iters", "lr", "batch_views", "num_frames", "fps", "eval_every", "batch_frames")
    mesh = DATASETS.build(cfg.data, device=ctx.device)
    if not isinstance(mesh, Mesh):
        raise UserError("sds_mesh needs a mesh data source (data=cube, data=mesh data.path=FILE, ...)")
    prior = load_prior(cfg, ctx.device)
    prompt = str(cfg.prompt)
    embedding = prior.embed_prompt(prompt)
    size = int(cfg.render_size) if int(cfg.render_size) > 0 else int(prior.image_size)
    field = TextureField(int(cfg.field.n_frequencies), int(cfg.field.hidden), int(cfg.field.layers)).to(ctx.device)
    renderer = FieldTextureRenderer(field, shading=str(cfg.shading), background=list(cfg.background),
                                    antialias=int(cfg.antialias))
    dist_range, elev_range, fov_range = (list(cfg[k]) for k in ("distance_range", "elevation_range", "fov_range"))
    cams_360 = turntable(int(cfg.num_frames), float(cfg.eval_distance), float(cfg.eval_elevation),
                         float(cfg.eval_fov), int(cfg.gif_size) or size, device=ctx.device)
    n_params = sum(p.numel() for p in field.parameters())

    def render_turntable(desc: str) -> torch.Tensor:
        return render_frames(renderer, mesh, cams_360, int(cfg.batch_frames), desc=desc, keys=("image",))["image"]

    with ctx.stopwatch.stage("render"):
        before = render_turntable("render before")
    score_before = score_frames(before, prompt)

    opt = torch.optim.Adam(field.parameters(), lr=float(cfg.lr))
    trainable = Trainable({"texture": field}, opt)

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        cams, _, _ = sample_orbit_cameras(int(cfg.batch_views), size, ctx.generator, distance=dist_range,
                                          elevation=elev_range, fov=fov_range, device=ctx.device)
        images = renderer(mesh, cams)["image"]                           # (B, H, W, 3)
        x = rgb_to_model_space(prior, images, channels_last=True)
        out = sds_loss(prior, x, embedding, float(cfg.guidance_scale), float(cfg.t_min), float(cfg.t_max),
                       generator=ctx.generator, on_nonfinite="flag")
        return {"loss": out.loss, "sds_grad_norm": torch.tensor(out.grad_norm),
                "t": out.t.float().mean()}

    def eval_fn(step: int) -> Dict[str, float]:
        idx = torch.linspace(0, len(cams_360) - 1, min(int(cfg.eval_views), len(cams_360))).round().long()
        frames = renderer(mesh, cams_360[idx.to(ctx.device)])["image"]
        ctx.logger.image("sds_mesh/front", frames[0], step)
        rate = score_frames(frames, prompt)["match"]
        return {} if rate is None else {"match_rate": rate}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, int(cfg.iters), eval_fn=eval_fn, eval_every=int(cfg.eval_every),
                       checkpoint_every=int(cfg.checkpoint_every), resume=bool(cfg.resume), desc="sds_mesh")
    with ctx.stopwatch.stage("render"):
        after = render_turntable("render after")
    score_after = score_frames(after, prompt)
    frames = torch.cat([before, after], dim=2)
    save_gif(ctx.path("sds_mesh.gif"), frames, fps=float(cfg.fps))
    save_png(ctx.path("after.png"), torch.cat(list(after[: min(8, len(after))]), dim=1))
    ctx.logger.image_sequence("sds_mesh/turntable", frames)
    if not bool(torch.isfinite(after).all()):
        raise UserError("the optimised texture rendered non-finite values")
    train_s = ctx.stopwatch.stages["train"]
    return {
        "prompt": prompt,
        "prior": str(cfg.prior.name),
        **score_metrics(score_after),
        "match_rate_before": score_before["match"],
        "guidance_scale": float(cfg.guidance_scale),
        "iters": result.step,
        "n_params": n_params,
        "train_seconds": round(train_s, 4),
        "seconds_per_iter": round(train_s / max(result.step, 1), 5),
        "render_size": size,
        "gif_size": int(cfg.gif_size) or size,
        "skipped_steps": result.skipped_steps,
        "history": result.history_rows(),
        "interrupted": result.interrupted,
    }

