"""view: a finished run (or a 3DGS PLY) served in the browser as ``viewer=true`` serves a training run.

``python main.py task=view checkpoint=RUN_DIR`` rebuilds the run's model from its
``.hydra/config.yaml`` and its weights (gs_train: ``point_cloud.ply``; train_nerf, volsdf:
``checkpoint.pt``), reads its data again for the training cameras (shown as frustums) and
serves the page at a printed local address until Ctrl+C (or ``seconds``).
``python main.py task=view ply=FILE`` serves a 3DGS PLY alone (no cameras; the page starts
outside the splats' robust radius).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.gaussian_ply import load_gaussian_ply
from l3d_app.models.gaussians import GaussianModel
from l3d_app.registry import DATASETS, DENSITIES, MODELS, SAMPLERS, TASKS
from l3d_app.render.sdf.density_choice import choose_density
from l3d_app.runtime.config_values import config_floats
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.checkpoints import CHECKPOINT, read_checkpoint
from l3d_app.models.background import background_parameter
from l3d_app.pipelines.live_viewer import gaussian_view, radiance_view, sdf_view, show_cameras, viewer_options
from l3d_app.viewer.live import LiveViewer

VIEWABLE = ("gs_train", "train_nerf", "volsdf")


def _run_config(run_dir: Path):
    from omegaconf import OmegaConf

    path = run_dir / ".hydra" / "config.yaml"
    if not path.is_file():
        raise UserError(f"{run_dir}: not a run directory (no .hydra/config.yaml)")
    return OmegaConf.load(path)


def _from_run(run_dir: Path, device) -> Tuple[object, object, str]:
    """(snapshot, render) of the run's final model, its data, and its task name."""
    cfg = _run_config(run_dir)
    task = str(cfg.get("task_name"))
    if task not in VIEWABLE:
        raise UserError(f"{run_dir}: a {task} run; task=view serves {', '.join(VIEWABLE)} runs")
    data = DATASETS.build(cfg.data).to(device)
    background = background_parameter(cfg.learn_background, data).to(device)
    if task == "gs_train":
        ply = run_dir / "point_cloud.ply"
        if not ply.is_file():
            raise UserError(f"{run_dir}: no point_cloud.ply (the run did not finish)")
        rgb = (_metrics(run_dir).get("background") or data.background.tolist())
        background["rgb"].data = torch.tensor(rgb, dtype=torch.float32, device=device)
        model = GaussianModel(**load_gaussian_ply(ply)).to(device)
        return gaussian_view(model, background["rgb"], lambda s: int(cfg.sh_degree), int(cfg.tile_size)), data, task
    ckpt = run_dir / CHECKPOINT
    if not ckpt.is_file():
        raise UserError(f"{run_dir}: no {CHECKPOINT} (the run did not finish)")
    state = read_checkpoint(ckpt)["trainable"]
    box = data.scene_box.tolist()
    model = MODELS.build(cfg.model, scene_box=box).to(device)
    sampler = SAMPLERS.build(cfg.sampler, scene_box=box).to(device)
    model.load_state_dict(state["modules"]["field"])
    background.load_state_dict(state["modules"]["background"])
    sampler.load_state_dict(state["extra"]["sampler"])
    model.eval()
    if task == "train_nerf":
        return radiance_view(model, sampler, background["rgb"], int(cfg.chunk)), data, task
    density_cfg, _ = choose_density(cfg.density, data)
    dens = DENSITIES.build(density_cfg).to(device)
    dens.load_state_dict(state["modules"]["density"])
    return sdf_view(model, sampler, dens, background["rgb"], int(cfg.chunk)), data, task


def _metrics(run_dir: Path) -> dict:
    import json

    p = run_dir / "metrics.json"
    return json.loads(p.read_text()) if p.is_file() else {}


@TASKS.register("view")
def view(cfg, ctx) -> dict:
    if bool(cfg.get("checkpoint")) == bool(cfg.get("ply")):
        raise UserError("task=view needs one of checkpoint=RUN_DIR (a gs_train, train_nerf or volsdf run) or ply=FILE")
    data, title = None, "view"
    if cfg.get("ply"):
        path = resolve_path(str(cfg.ply))
        if not path.is_file():
            raise UserError(f"PLY file not found: {path}")
        model = GaussianModel(**load_gaussian_ply(path)).to(ctx.device)
        bg = torch.tensor(config_floats(cfg.background, "background", 3), device=ctx.device)
        (snapshot, render), title = gaussian_view(model, bg, lambda s: int(cfg.sh_degree), 16), path.name
    else:
        run_dir = resolve_path(str(cfg.checkpoint))
        if not run_dir.is_dir():
            raise UserError(f"run directory not found: {run_dir}")
        (snapshot, render), data, task = _from_run(run_dir, ctx.device)
        title = f"{task}: {run_dir.name}"
    live = LiveViewer(lambda: snapshot(0), render, title=title, **viewer_options(cfg))
    if data is not None:
        show_cameras(live, data)
    else:
        _look_at_splats(live, model)
    live.publish(int(_metrics(resolve_path(str(cfg.checkpoint))).get("iters", 0)) if cfg.get("checkpoint") else 0)
    print(f"l3d_app: viewer: {live.url} ({title}; Ctrl+C stops)", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    try:
        while float(cfg.seconds) <= 0 or time.perf_counter() - t0 < float(cfg.seconds):
            time.sleep(0.2)
    finally:
        live.close()
    return {"url": live.url, "served_seconds": round(time.perf_counter() - t0, 2)}


def _look_at_splats(live: LiveViewer, model: GaussianModel) -> None:
    """Start the pages outside the splats' robust (90th percentile) radius, looking at their centre."""
    with torch.no_grad():
        w = torch.sigmoid(model.opacity_logits)
        centre = (model.means * w[:, None]).sum(0) / w.sum().clamp_min(1e-12)
        radius = max(float((model.means - centre).norm(dim=-1).quantile(0.9)), 1e-6)
    c = centre.cpu().tolist()
    live.server.initial_camera.look_at = tuple(c)
    live.server.initial_camera.position = (c[0], c[1] - 2.5 * radius, c[2] + 0.5 * radius)
