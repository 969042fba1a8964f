"""A finished run's renderer: rebuild a trained model from its config and checkpoint.

:func:`run_renderer` takes a run's resolved config (a plain mapping: its ``.hydra/config.yaml``) and
its checkpoint's ``trainable`` state, rebuilds the data source and the model through the registries,
and returns ``render(cameras) -> {"color", "depth", "alpha"}`` rendered as the task evaluated. The
per-kind adapters below are thin (one per trained task: ``train_nerf``, ``volsdf``, ``gs_train``);
a new trained kind adds one.
"""

from __future__ import annotations

from typing import Any, Callable, Dict, Mapping, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import camera_rays
from l3d_app.registry import DATASETS, DENSITIES, MODELS, SAMPLERS

Render = Callable[[Cameras], Dict[str, torch.Tensor]]


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
    sampler = SAMPLERS.build(conf["sampler"], scene_box=box).to(device)
    saved = state.get("extra", {}).get("sampler")
    if saved is not None and hasattr(sampler, "load_state_dict"):
        sampler.load_state_dict(saved)
    return sampler


def _nerf(conf, state, data, device, chunk) -> Render:
    from l3d_app.render.volume.radiance import render_field_rays

    box = data.scene_box.tolist()
    model = MODELS.build(conf["model"], scene_box=box).to(device).eval()
    model.load_state_dict(state["modules"]["field"])
    sampler, background = _sampler(conf, state, box, device), _background(state, data, device)
    return _field_renderer(lambda o, d: render_field_rays(model, o, d, sampler, background=background), chunk)


def _volsdf(conf, state, data, device, chunk) -> Render:
    return _field_renderer(volsdf_rays(conf, state, data, device), chunk, normalize=False)


def volsdf_rays(conf, state, data, device):
    """A volsdf run's ``fn(origins, dirs)`` (camera-Z = 1 directions), rendered as its evaluation does."""
    from l3d_app.models.sdf_gradients import field_with_gradient
    from l3d_app.render.sdf.density_choice import choose_density
    from l3d_app.render.sdf.volume import render_sdf_rays

    box = data.scene_box.tolist()
    model = MODELS.build(conf["model"], scene_box=box).to(device).eval()
    model.load_state_dict(state["modules"]["field"])
    dens = DENSITIES.build(choose_density(conf["density"], data)[0]).to(device)   # density=auto: as the run chose
    dens.load_state_dict(state["modules"]["density"])
    sampler, background = _sampler(conf, state, box, device), _background(state, data, device)
    # as volsdf does before its test views: the SDF cache is refreshed from the final field (the
    # checkpointed copy can be up to `every` steps old, and evaluation renders skip the rays it calls empty)
    sampler.update(int(state.get("step", 0)), model, None, force=True)
    field_fn = field_with_gradient(model)
    return lambda o, d: render_sdf_rays(field_fn, o, d, sampler, dens, field=model, background=background)


def gaussian_renderer(model, sh_degree: int, background, tile_size: int = 4) -> Render:
    """``render(cameras)`` of a :class:`~l3d_app.models.gaussians.GaussianModel` at ``sh_degree``."""
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
    return gaussian_renderer(model.to(device), int(conf["sh_degree"]), _background(state, data, device),
                             int(conf.get("tile_size", 4)))


ADAPTERS = {"train_nerf": _nerf, "volsdf": _volsdf, "gs_train": _gaussians}


def run_renderer(conf: Mapping[str, Any], state: Mapping[str, Any], device, chunk: int, source: str = "the run"
                 ) -> Tuple[Render, Any, str]:
    """(render, data, task name) of a finished run: ``conf`` its resolved config, ``state`` its checkpoint's
    ``trainable`` state, ``chunk`` rays per render call; ``source`` names the config in errors."""
    kind = str(conf.get("task_name"))
    if kind not in ADAPTERS:
        raise UserError(f"{source}: render_path renders runs of {', '.join(ADAPTERS)}, not {kind}")
    data = DATASETS.build(conf["data"]).to(device)
    with torch.no_grad():
        return ADAPTERS[kind](conf, state, data, device, chunk), data, kind
