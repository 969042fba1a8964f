"""Pieces shared by the fitting tasks (fit_vox, fit_point, fit_mesh): the target, the
held-out val / test samples of its surface, the Adam fit with its val / test evaluations, the
side-by-side turntable of fit and target, and the common knob checks."""

from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple, Union

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.sampling import sample_points_on_mesh
from l3d_app.registry import CAMERA_PATHS, DATASETS, RENDERERS
from l3d_app.render.evaluation import render_frames
from l3d_app.render.previews import frames_within_budget
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.media import save_gif
from l3d_app.runtime.random import held_out_seed
from l3d_app.runtime.training import Trainable, TrainResult, log_test, train
from l3d_app.tasks.common import check_output_knobs, loop_spec, require_nonnegative, require_positive

Shape = Union[Mesh, PointCloud, None]


def load_target_mesh(cfg, device) -> Mesh:
    """The data source's mesh (built-in shape or ``data=mesh data.path=FILE``)."""
    mesh = DATASETS.build(cfg.data, device=device)
    if not isinstance(mesh, Mesh):
        raise UserError("fitting tasks need a mesh data source (data=builtin, data=mesh data.path=FILE, ...)")
    return mesh


def eval_generator(cfg, device, split: str = "test", stream: int = 0) -> torch.Generator:
    """A generator for held-out evaluation samples, independent of the training draws and
    the same for every run with that seed: seeded :func:`~l3d_app.runtime.random.held_out_seed`
    (``seed * 1000 + eval_seed_offset + 2 * stream``, plus one for ``split="val"``), so that the val
    and test streams (and a task's further ``stream`` s, e.g. draws on the fitted surface) never
    share a draw, within a run or across seeds."""
    seed = held_out_seed(int(cfg.seed), int(cfg.eval_seed_offset), split, int(stream))
    return torch.Generator(device="cpu").manual_seed(seed)   # CPU: the same draws on any device


def held_out_surface(mesh: Mesh, n: int, cfg, device) -> Dict[str, torch.Tensor]:
    """Samples of the target surface that training never sees, each ``(n, 3)`` world units:
    ``val`` (read by the periodic evaluation), ``test`` (read once, at the end) and
    ``test_other`` (a second test-side sampling: the sampling floor ``chamfer_baseline``)."""
    gen_test, gen_val = eval_generator(cfg, device, "test"), eval_generator(cfg, device, "val")
    test = sample_points_on_mesh(mesh, n, gen_test).points
    other = sample_points_on_mesh(mesh, n, gen_test).points
    return {"val": sample_points_on_mesh(mesh, n, gen_val).points, "test": test, "test_other": other}


def fit_and_test(cfg, ctx, task: str, name: str, holder: torch.nn.ParameterDict,
                 step: Callable[[int], Dict[str, torch.Tensor]],
                 evaluate_on: Callable[[str], Dict[str, float]]) -> Tuple[TrainResult, Dict[str, float]]:
    """Adam over ``holder`` (checkpointed as ``name``) at ``lr``, cosine-decayed to ``lr_final`` over
    ``iters``; the shared loop of ``task`` runs ``step`` and ``evaluate_on("val")`` every ``eval_every``
    steps under a time budget that keeps one validation's worth for the test figures; then
    ``evaluate_on("test")``, read once and logged. Returns the loop's result and the test figures."""
    opt = torch.optim.Adam(holder.parameters(), lr=float(cfg.lr))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=int(cfg.iters), eta_min=float(cfg.lr_final))
    trainable = Trainable({name: holder}, opt, schedulers=[sched])
    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step, loop_spec(cfg, task), lambda _i: evaluate_on("val"),
                       budget=TimeBudget.of(ctx).keep_renders(1))      # the test figures cost what a validation does
    final = evaluate_on("test")
    log_test(ctx, final, result.step)
    return result, final


def check_fit_knobs(cfg, *extra: str) -> None:
    """Positive sizes and counts (``extra``: the task's own); loss weights (``w_*``) and the final
    learning rate, where the task has them, >= 0 (a negative weight would maximise its loss)."""
    require_positive(cfg, "iters", "image_size", "num_frames", "fps", "batch_frames", *extra)
    check_output_knobs(cfg)
    require_nonnegative(cfg, *(k for k in cfg if str(k).startswith("w_") or k == "lr_final"))


def _render(cfg, shape: Shape, cams, desc: str) -> torch.Tensor:
    """(N, H, W, 3) frames of a Mesh (``renderer``), a PointCloud (``point_renderer``), or a
    blank background when ``shape`` is None (e.g. an empty fit)."""
    if shape is None:
        bg = torch.tensor(list(cfg.background), dtype=torch.float32)
        return bg.expand(len(cams), cams.height, cams.width, 3).clone()
    renderer = RENDERERS.build(cfg.renderer if isinstance(shape, Mesh) else cfg.point_renderer)
    return render_frames(renderer, shape, cams, int(cfg.batch_frames), desc=desc)["image"]


def side_by_side_turntable(cfg, ctx, fitted: Shape, target: Shape, name: str) -> Optional[torch.Tensor]:
    """Write ``name`` (gif): turntable of ``fitted`` (left) beside ``target`` (right); log it. Under
    a time budget only the frames that still fit (:func:`frames_within_budget`).

    Returns the (N, H, 2W, 3) frames, or None when no frame fit the budget (no gif).
    """
    cams = CAMERA_PATHS.build(cfg.camera, device=ctx.device)

    def render(c) -> torch.Tensor:
        with torch.no_grad():
            return torch.cat([_render(cfg, fitted, c, "render fit"), _render(cfg, target, c, "render target")], dim=2)

    frames = frames_within_budget(TimeBudget.of(ctx), cams, render, f"{name.rsplit('.', 1)[0]}/budget")
    if frames is None:
        return None
    save_gif(ctx.path(name), frames, fps=float(cfg.fps))
    ctx.logger.image_sequence(f"{name.rsplit('.', 1)[0]}/frames", frames)
    return frames
