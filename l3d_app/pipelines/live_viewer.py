"""The live viewer wired into a training task (``viewer=true``) and into ``task=view``.

A task adds two lines: ``live = start_viewer(cfg, ctx, data, *gaussian_view(...))`` (or
:func:`field_view`) after building its model, and ``finish_viewer(live, ctx, step)`` after
training. The viewer watches the run's logger (``ctx.logger.watchers``), so the training loop
is unchanged: it learns the step, the loss and the validation PSNR from what the loop logs and
snapshots the model on the training thread only while a page is open
(:class:`~l3d_app.viewer.live.LiveViewer`).
"""

from __future__ import annotations

import copy
import sys
from typing import Any, Callable, Dict, Optional, Tuple

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.models.sdf_gradients import field_with_gradient
from l3d_app.render.evaluation import render_views
from l3d_app.render.gaussians.rasterize import rasterize_gaussians
from l3d_app.render.sdf.volume import render_sdf_rays
from l3d_app.render.volume.radiance import render_field_rays
from l3d_app.viewer.live import LiveViewer

Snapshot = Callable[[int], Any]
Render = Callable[[Any, Cameras], torch.Tensor]


def viewer_options(cfg) -> Dict[str, Any]:
    """LiveViewer keyword arguments from the optional ``+viewer_port`` / ``+viewer_width`` (px) /
    ``+viewer_period`` (s) overrides; LiveViewer's own defaults otherwise."""
    kinds = {"port": int, "width": int, "period": float}
    return {"host": "127.0.0.1", **{k: kind(cfg[f"viewer_{k}"]) for k, kind in kinds.items() if f"viewer_{k}" in cfg}}


def start_viewer(cfg, ctx, data, snapshot: Snapshot, render: Render, title: Optional[str] = None) -> Optional[LiveViewer]:
    """Serve the live page when ``cfg.viewer`` is true (else None): the training cameras of ``data``
    as frustums, the model from ``snapshot`` drawn by ``render``; prints the address."""
    if not bool(cfg.get("viewer", False)):
        return None
    step = {"now": 0}
    live = LiveViewer(lambda: snapshot(step["now"]), render, title=title or str(cfg.get("task_name", "l3d_app")),
                      **viewer_options(cfg))
    show_cameras(live, data)
    live.watcher = lambda tag, value, s: (step.__setitem__("now", int(s)), live.observe(tag, value, s))
    ctx.logger.watchers.append(live.watcher)
    print(f"l3d_app: viewer: {live.url} (the model as it trains, from your browser's camera)", file=sys.stderr, flush=True)
    return live


def show_cameras(live: LiveViewer, data) -> None:
    """The training cameras of ``data`` as frustums sized to their spread; pages start at the first."""
    tr = data.train.to(data.cameras.device) if len(data.train) else torch.arange(len(data.cameras))
    cams = data.cameras[tr].to(device="cpu")
    centres = cams.centers().double()
    spread = float((centres - centres.mean(0)).norm(dim=-1).median()) if len(centres) > 1 else 1.0
    box = data.scene_box.detach().cpu().double()
    live.add_cameras(cams, scale=0.08 * max(spread, 1e-3), up=data.up.detach().cpu(), look_at=box.mean(0))


def finish_viewer(live: Optional[LiveViewer], ctx, step: int) -> None:
    """After training: show the final model once more, then stop serving."""
    if live is None:
        return
    ctx.logger.watchers.remove(live.watcher)
    live.close()
    print(f"l3d_app: viewer closed; serve the finished run with: python main.py task=view checkpoint={ctx.out_dir}",
          file=sys.stderr, flush=True)


def gaussian_view(model, background: torch.Tensor, degree: Callable[[int], int], tile_size: int,
                  rasterize: Callable = rasterize_gaussians) -> Tuple[Snapshot, Render]:
    """(snapshot, render) of a :class:`~l3d_app.models.gaussians.GaussianModel` with a background RGB (3,),
    drawn by ``rasterize`` (3D Gaussians; :func:`~l3d_app.render.gaussians.surfels.rasterize_surfels` for surfels)."""
    def snapshot(step: int) -> Dict[str, Any]:
        with torch.no_grad():
            return {"means": model.means.detach().clone(), "log_scales": model.log_scales3.detach().clone(),
                    "quats": model.quats.detach().clone(), "opacity": model.opacity_logits.detach().clone(),
                    "sh": model.sh.detach().clone(), "degree": int(degree(step)),
                    "background": background.detach().clamp(0, 1).clone()}

    def render(s: Dict[str, Any], camera: Cameras) -> torch.Tensor:
        return rasterize(s["means"], s["log_scales"], s["quats"], s["opacity"], s["sh"], s["degree"],
                         camera.to(device=s["means"].device), s["background"], tile_size=int(tile_size))["color"][0]

    return snapshot, render


def field_view(parts: Dict[str, Any], make_render: Callable[[Dict[str, Any]], Callable], chunk: int
               ) -> Tuple[Snapshot, Render]:
    """(snapshot, render) of a ray-rendered field: ``parts`` (modules, samplers, tensors) are deep-copied
    on the training thread; ``make_render(copy)`` returns ``render_fn(origins, dirs) -> {"color", ...}``."""
    device = next((p.device for v in parts.values() if isinstance(v, torch.nn.Module) for p in v.parameters()),
                  torch.device("cpu"))

    def snapshot(step: int) -> Dict[str, Any]:
        with torch.no_grad():
            return copy.deepcopy(parts)

    def render(s: Dict[str, Any], camera: Cameras) -> torch.Tensor:
        return render_views(make_render(s), camera.to(device=device), int(chunk))["color"][0]

    return snapshot, render


def radiance_view(model, sampler, background: torch.Tensor, chunk: int) -> Tuple[Snapshot, Render]:
    """(snapshot, render) of a radiance field with its sampler and background RGB (train_nerf)."""
    def make(p):
        return lambda o, d, **kw: render_field_rays(p["field"], o, d, p["sampler"], background=p["bg"].clamp(0, 1),
                                                    density_field=p["field"], **kw)

    return field_view({"field": model, "sampler": sampler, "bg": background}, make, chunk)


def sdf_view(model, sampler, density, background: torch.Tensor, chunk: int) -> Tuple[Snapshot, Render]:
    """(snapshot, render) of an SDF field rendered through ``density`` (volsdf)."""
    def make(p):
        field_fn = field_with_gradient(p["field"])
        return lambda o, d, **kw: render_sdf_rays(field_fn, o, d, p["sampler"], p["density"], field=p["field"],
                                                  background=p["bg"].clamp(0, 1), **kw)

    return field_view({"field": model, "sampler": sampler, "density": density, "bg": background}, make, chunk)
