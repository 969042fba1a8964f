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

The per-kind renderers below are thin adapters over the library's render functions (one
``render(cams) -> {color, depth, alpha}`` each); a new trained kind adds one adapter.
"""

from __future__ import annotations

import time
from typing import Callable, Dict

import numpy as np
import torch
from omegaconf import OmegaConf

from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import (interpolate_cameras, orbit, read_camera_path, spiral,
                                           write_camera_path)
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import camera_rays
from l3d_app.registry import DATASETS, DENSITIES, MODELS, SAMPLERS, TASKS
from l3d_app.render.sdf.density_choice import choose_density
from l3d_app.runtime.checkpoints import read_checkpoint
from l3d_app.runtime.config_values import config_floats, config_words
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.media import save_gif, to_uint8
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.progress import progress

Render = Callable[[Cameras], Dict[str, torch.Tensor]]
PATHS = ("orbit", "spiral", "interp", "camera_path")
PANELS = ("color", "depth", "alpha")


# ------------------------------------------------------------ per-kind adapters
def _field_renderer(fn, chunk: int, normalize: bool = True) -> Render:
    """Render cameras with ``fn(origins, dirs)``; ``normalize``: unit directions (train_nerf) or
    camera-Z = 1 directions (volsdf), as the task trained with."""
    from l3d_app.render.volume.renderer import render_rays_chunked

    def keep(o, d):
        return {k: v for k, v in fn(o, d).items() if k in ("color", "depth", "opacity")}

    def render(cams: Cameras) -> Dict[str, torch.Tensor]:
        o, d = camera_rays(cams, normalize=normalize)
        out = render_rays_chunked(keep, o, d, chunk)
        return {"color": out["color"], "depth": out["depth"], "alpha": out["opacity"]}
    return render


def _background(state, data, device) -> torch.Tensor:
    """(3,) the run's learnt background (``learn_background``) when it saved one, else the data's."""
    saved = state["modules"].get("background", {}).get("rgb")
    return (saved if saved is not None else data.background).to(device).float().clamp(0, 1)


def _sampler(conf, state, box, device):
    """The run's ray sampler (occupancy grid / SDF cache) with its checkpointed state."""
    sampler = SAMPLERS.build(conf.sampler, scene_box=box).to(device)
    saved = state.get("extra", {}).get("sampler")
    if saved is not None and hasattr(sampler, "load_state_dict"):
        sampler.load_state_dict(saved)
    return sampler


def _nerf(conf, state, data, device, chunk) -> Render:
    from l3d_app.render.volume.radiance import render_field_rays

    box = data.scene_box.tolist()
    model = MODELS.build(conf.model, scene_box=box).to(device).eval()
    model.load_state_dict(state["modules"]["field"])
    sampler, background = _sampler(conf, state, box, device), _background(state, data, device)
    return _field_renderer(lambda o, d: render_field_rays(model, o, d, sampler, background=background), chunk)


def _volsdf(conf, state, data, device, chunk) -> Render:
    return _field_renderer(volsdf_rays(conf, state, data, device), chunk, normalize=False)


def volsdf_rays(conf, state, data, device):
    """A volsdf run's ``fn(origins, dirs)`` (camera-Z = 1 directions), rendered as its evaluation does."""
    from l3d_app.models.sdf_gradients import field_with_gradient
    from l3d_app.render.sdf.volume import render_sdf_rays

    box = data.scene_box.tolist()
    model = MODELS.build(conf.model, scene_box=box).to(device).eval()
    model.load_state_dict(state["modules"]["field"])
    dens = DENSITIES.build(choose_density(conf.density, data)[0]).to(device)   # density=auto: as the run chose
    dens.load_state_dict(state["modules"]["density"])
    sampler, background = _sampler(conf, state, box, device), _background(state, data, device)
    # as volsdf does before its test views: the SDF cache is refreshed from the final field (the
    # checkpointed copy can be up to `every` steps old, and evaluation renders skip the rays it calls empty)
    sampler.update(int(state.get("step", 0)), model, None, force=True)
    field_fn = field_with_gradient(model)
    return lambda o, d: render_sdf_rays(field_fn, o, d, sampler, dens, field=model, background=background)


def _gaussian_renderer(model, sh_degree: int, background, tile_size: int = 4) -> Render:
    from l3d_app.render.gaussians.rasterize import rasterize_gaussians

    def render(cams: Cameras) -> Dict[str, torch.Tensor]:
        out = rasterize_gaussians(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh,
                                  sh_degree, cams, background, tile_size=tile_size)
        return {"color": out["color"], "depth": out["depth"], "alpha": out["alpha"]}
    return render


def _gaussians(conf, state, data, device, chunk) -> Render:
    from l3d_app.models.gaussians import GaussianModel

    sd = state["modules"]["gaussians"]
    model = GaussianModel(*(sd[k] for k in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")))
    return _gaussian_renderer(model.to(device), int(conf.sh_degree), _background(state, data, device),
                              int(conf.get("tile_size", 4)))


ADAPTERS = {"train_nerf": _nerf, "volsdf": _volsdf, "gs_train": _gaussians}


def load_run(run_dir, device, chunk: int):
    """(render, data, task name) of a finished run directory."""
    run = resolve_path(str(run_dir))
    cfg_file, ckpt = run / ".hydra" / "config.yaml", run / "checkpoint.pt"
    for f in (cfg_file, ckpt):
        if not f.is_file():
            raise UserError(f"checkpoint run directory {run} has no {f.relative_to(run)}")
    conf = OmegaConf.load(cfg_file)
    kind = str(conf.get("task_name"))
    if kind not in ADAPTERS:
        raise UserError(f"{cfg_file}: render_path renders runs of {', '.join(ADAPTERS)}, not {kind}")
    state = read_checkpoint(ckpt)["trainable"]
    data = DATASETS.build(conf.data).to(device)
    with torch.no_grad():
        return ADAPTERS[kind](conf, state, data, device, chunk), data, kind


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


# ----------------------------------------------------------------- output
def panel_frames(out: Dict[str, torch.Tensor], panels) -> torch.Tensor:
    """(N, H, W * len(panels), 3) frames in [0, 1] from colour, depth, alpha (N, H, W[, 3])."""
    alpha = out["alpha"].clamp(0, 1)
    depth = out["depth"] / alpha.clamp_min(1e-6)
    hit = alpha > 0.5
    if bool(hit.any()):
        q = torch.quantile(depth[hit].float()[:1_000_000], torch.tensor([0.02, 0.98]))
        lo, hi = float(q[0]), float(q[1])
    else:
        lo, hi = 0.0, 1.0
    gray = torch.where(hit, (1.0 - 0.8 * (depth - lo) / max(hi - lo, 1e-6)).clamp(0.2, 1.0), torch.zeros_like(depth))
    parts = {"color": out["color"].clamp(0, 1), "depth": gray[..., None].expand(*gray.shape, 3),
             "alpha": alpha[..., None].expand(*alpha.shape, 3)}
    return torch.cat([parts[p] for p in panels], dim=2)


def save_mp4(path, frames: torch.Tensor, fps: float) -> None:
    """(N, H, W, 3) in [0, 1] -> H.264 mp4 (padded to even sizes), written atomically."""
    import imageio.v2 as imageio

    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError as err:
        raise UserError("mp4 output needs imageio-ffmpeg: pip install imageio-ffmpeg (or formats=[gif])") from err
    x = to_uint8(frames)
    ph, pw = x.shape[1] % 2, x.shape[2] % 2
    x = np.pad(x, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")
    with atomic_path(path) as tmp:
        imageio.mimwrite(tmp, list(x), fps=float(fps), codec="libx264", macro_block_size=1,
                         ffmpeg_log_level="error", output_params=["-pix_fmt", "yuv420p"])


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
        render, kind = _gaussian_renderer(ply_model, int(cfg.sh_degree), background), "ply"
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
