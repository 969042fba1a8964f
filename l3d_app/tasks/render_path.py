"""render_path: render a trained model along a camera path, as mp4 and gif.

``python main.py task=render_path checkpoint=RUN_DIR path=orbit|spiral|interp|camera_path
[camera_path=FILE.json]`` or ``ply=FILE`` (any 3DGS PLY) instead of ``checkpoint``.

``RUN_DIR`` is a run of ``train_nerf`` (or ``nerf_baseline``), ``volsdf`` or ``gs_train``: its
``.hydra/config.yaml`` rebuilds the data source and the model through the registries, and
``checkpoint.pt`` restores the weights. Paths (:mod:`l3d_app.geometry.camera_paths`) turn
about the data's ``up`` vector around the scene box centre, at the training cameras' median
distance times ``radius_scale`` and (``elevation: null``) their mean elevation; ``interp``
passes through ``interp_keys`` training cameras; ``camera_path`` reads a nerfstudio
``camera_path.json`` in the data's world frame. Frames are ``panels`` side by side: colour |
depth (expected depth over covered pixels, white = near, normalised over the whole path) |
alpha. Writes ``path.mp4`` (imageio-ffmpeg), ``path.gif``, the cameras used as
``camera_path.json`` and ``metrics.json`` (frames, seconds, frames_per_second).

The run's renderer is :func:`l3d_app.pipelines.runs.run_renderer`; this task reads the run
directory, builds the path and writes the frames.
"""

from __future__ import annotations

import time

import torch
from omegaconf import OmegaConf

from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import (interpolate_cameras, orbit, read_camera_path, spiral,
                                           write_camera_path)
from l3d_app.geometry.cameras import Cameras
from l3d_app.pipelines.runs import gaussian_renderer, run_renderer
from l3d_app.registry import TASKS
from l3d_app.render.evaluation import panel_frames
from l3d_app.runtime.checkpoints import read_checkpoint
from l3d_app.runtime.config_values import config_floats, config_words
from l3d_app.runtime.media import save_gif, save_mp4
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.progress import progress

PATHS = ("orbit", "spiral", "interp", "camera_path")
PANELS = ("color", "depth", "alpha")


def load_run(run_dir, device, chunk: int):
    """(render, data, task name) of a finished run directory (its ``.hydra/config.yaml`` and ``checkpoint.pt``)."""
    run = resolve_path(str(run_dir))
    cfg_file, ckpt = run / ".hydra" / "config.yaml", run / "checkpoint.pt"
    for f in (cfg_file, ckpt):
        if not f.is_file():
            raise UserError(f"checkpoint run directory {run} has no {f.relative_to(run)}")
    conf = OmegaConf.to_container(OmegaConf.load(cfg_file), resolve=True)
    return run_renderer(conf, read_checkpoint(ckpt)["trainable"], device, chunk, source=str(cfg_file))


# ----------------------------------------------------------------- the path
def make_path(cfg, data, ply_model=None) -> Cameras:
    """The cameras of ``cfg.path`` about the data (or, for a PLY, about the splats)."""
    name = str(cfg.path)
    if name not in PATHS:
        raise UserError(f"path must be one of {', '.join(PATHS)}, got {name!r}")
    if name == "camera_path":
        if not cfg.get("camera_path"):
            raise UserError("path=camera_path needs camera_path=FILE.json (nerfstudio layout)")
        return read_camera_path(resolve_path(str(cfg.camera_path)))
    n = int(cfg.num_frames)
    if data is not None:
        cams, up = data.cameras[data.train.to(data.cameras.device)].to(device="cpu"), data.up.cpu().double()
        centre = data.scene_box.cpu().double().mean(0)
        offs = cams.centers().double() - centre
        radius = float(offs.norm(dim=-1).median())
        elev = float(torch.rad2deg(torch.asin((torch.nn.functional.normalize(offs, dim=-1) @ up).clamp(-1, 1))).mean())
        fov, (H, W), start = float(cams.fov()[0]), data.image_size, offs[0]
    else:
        w = torch.sigmoid(ply_model.opacity_logits.detach().reshape(-1)).cpu().double()
        means = ply_model.means.detach().cpu().double()
        centre = (means * w[:, None]).sum(0) / w.sum().clamp_min(1e-12)
        radius = 2.5 * float((means - centre).norm(dim=-1).quantile(0.9))
        up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        elev, fov, (H, W), start = 20.0, 50.0, (256, 256), None
        cams = None
    if cfg.get("up") is not None:
        up = torch.tensor(config_floats(cfg.up, "up", 3), dtype=torch.float64)
    if int(cfg.image_size) > 0:
        H, W = int(cfg.image_size), max(1, int(round(int(cfg.image_size) * W / H)))
    el = float(cfg.elevation) if cfg.get("elevation") is not None else elev
    r = float(cfg.radius_scale) * radius
    if name == "orbit":
        return orbit(n, centre, up, r, el, fov, W, H, start=start)
    if name == "spiral":
        return spiral(n, centre, up, r, el, fov, W, H, rounds=float(cfg.spiral.rounds),
                      elevation_amplitude=float(cfg.spiral.elevation_amplitude),
                      radius_amplitude=float(cfg.spiral.radius_amplitude), start=start)
    if cams is None:
        raise UserError("path=interp needs a checkpoint's training cameras (not a bare PLY)")
    k = max(2, min(int(cfg.interp_keys), len(cams)))
    keys = cams[torch.linspace(0, len(cams) - 1, k).round().long()]
    if int(cfg.image_size) > 0:
        s = H / keys.height
        keys = Cameras(keys.R, keys.t, keys.fx * s, keys.fy * s, keys.cx * s, keys.cy * s, W, H)
    return interpolate_cameras(keys, n, closed=True)


@TASKS.register("render_path")
def render_path(cfg, ctx) -> dict:
    """Render the path's frames, write mp4 / gif / camera_path.json."""
    panels, formats = config_words(cfg.panels, "panels"), config_words(cfg.formats, "formats")
    bad = [p for p in panels if p not in PANELS] + [f for f in formats if f not in ("mp4", "gif")]
    if bad or not panels or not formats:
        raise UserError(f"panels must be from {list(PANELS)} and formats from ['mp4', 'gif'], neither empty; "
                        f"got panels={panels}, formats={formats}")
    if cfg.get("up") is not None:
        config_floats(cfg.up, "up", 3)
    background = config_floats(cfg.background, "background", 3)
    if int(cfg.num_frames) <= 0:
        raise UserError(f"num_frames must be positive, got {cfg.num_frames}")
    data, ply_model = None, None
    if cfg.get("ply"):
        from l3d_app.geometry.gaussian_ply import load_gaussian_ply
        from l3d_app.models.gaussians import GaussianModel

        ply = resolve_path(str(cfg.ply))
        if not ply.is_file():
            raise UserError(f"PLY file not found: {ply}")
        ply_model = GaussianModel(**load_gaussian_ply(ply)).to(ctx.device)
        render, kind = gaussian_renderer(ply_model, int(cfg.sh_degree), background), "ply"
    elif cfg.get("checkpoint"):
        render, data, kind = load_run(cfg.checkpoint, ctx.device, int(cfg.chunk))
    else:
        raise UserError("render_path needs checkpoint=RUN_DIR (a train_nerf / volsdf / gs_train run) or ply=FILE")
    cams = make_path(cfg, data, ply_model).to(ctx.device)
    outs = []
    t0 = time.perf_counter()
    with torch.no_grad():
        for i in progress(range(len(cams)), desc="render_path", total=len(cams)):
            outs.append({k: v.cpu() for k, v in render(cams[i]).items()})
    seconds = time.perf_counter() - t0
    out = {k: torch.cat([o[k] for o in outs]) for k in ("color", "depth", "alpha")}
    if not all(bool(torch.isfinite(v).all()) for v in out.values()):
        raise UserError("the render produced non-finite values (a diverged checkpoint?)")
    frames = panel_frames(out, panels)
    if "mp4" in formats:
        save_mp4(ctx.path("path.mp4"), frames, float(cfg.fps))
    if "gif" in formats:
        save_gif(ctx.path("path.gif"), frames, fps=float(cfg.fps))
    write_camera_path(ctx.path("camera_path.json"), cams.to(device="cpu"), fps=float(cfg.fps))
    ctx.logger.image_sequence("render_path/frames", frames)
    return {"source": kind, "path": str(cfg.path), "num_frames": len(cams), "render_seconds": round(seconds, 3),
            "frames_per_second": round(len(cams) / max(seconds, 1e-9), 3),
            "coverage": round(float(out["alpha"].mean()), 5)}
