"""Shaded renders of a radiance field (DreamFusion-style): albedo, Lambertian, textureless or
normal shading with normals from the density gradient, plus the orientation penalty, all
composited by :func:`~l3d_app.render.volume.rendering.render_rays` as one 7-channel "colour"
(colour 3 | orientation penalty 1 | normal 3).
"""

from __future__ import annotations

from typing import Callable, Dict, Optional

import torch
import torch.nn.functional as F

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import camera_rays
from l3d_app.render.volume.estimators import StratifiedEstimator
from l3d_app.render.volume.radiance import render_field_rays
from l3d_app.render.volume.renderer import render_rays_chunked
from l3d_app.runtime.random import rand

SHADINGS = ("albedo", "lambertian", "textureless", "normal")
SCENE_BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
# channels of the shaded field's output: colour (3) | orientation penalty (1) | normal (3)
N_CHANNELS = 7


def shaded_field(field: torch.nn.Module, shading: str, light_offset: torch.Tensor, ambient: float,
                 need_normals: bool, create_graph: bool, normals_fn: Callable, penalty_fn: Callable) -> Callable:
    """A field callable for the volume renderer returning ``N_CHANNELS`` per sample:
    shaded colour (3), orientation penalty (1) and unit normal (3).

    ``normals_fn(sigma (N,), points (N, 3), create_graph) -> (N, 3)`` unit normals and
    ``penalty_fn(normals, dirs) -> (N,)`` the orientation penalty are given by the caller
    (e.g. :mod:`l3d_app.losses.nerf_regularizers`' ``density_normals`` / ``orientation_penalty``;
    render code does not import losses).

    ``light_offset`` (3,) is added to the direction towards the camera (``-dirs``) to make
    the light direction. Without ``need_normals`` (albedo only) the last 4 channels are 0.
    """
    if shading not in SHADINGS:
        raise UserError(f"unknown shading '{shading}' (known: {', '.join(SHADINGS)})")
    need_normals = need_normals or shading != "albedo"

    def fn(points: torch.Tensor, dirs: torch.Tensor):
        if not need_normals:
            sigma, albedo = field(points, dirs)
            return sigma, torch.cat([albedo, albedo.new_zeros(albedo.shape[0], 4)], dim=-1)
        with torch.enable_grad():
            x = points.detach().requires_grad_(True)
            sigma, albedo = field(x, dirs)
            normals = normals_fn(sigma, x, create_graph=create_graph)
        if not create_graph:
            sigma, albedo, normals = sigma.detach(), albedo.detach(), normals.detach()
        light = F.normalize(-dirs + light_offset.to(dirs), dim=-1)
        diffuse = ambient + (1.0 - ambient) * (normals * light).sum(-1, keepdim=True).clamp_min(0.0)
        if shading == "albedo":
            colour = albedo
        elif shading == "lambertian":
            colour = albedo * diffuse
        elif shading == "textureless":
            colour = diffuse.expand(-1, 3)
        else:
            colour = (normals + 1.0) / 2.0
        orient = penalty_fn(normals, dirs)[:, None]
        return sigma, torch.cat([colour, orient, normals], dim=-1)

    return fn


def render_shaded_views(field: torch.nn.Module, cams: Cameras, shading: str, *, n_samples: int, background,
                        light_offset: Optional[torch.Tensor] = None, ambient: float = 0.3,
                        need_normals: bool = True, training: bool = False,
                        generator: Optional[torch.Generator] = None, chunk: int = 0,
                        estimator=None, normals_fn: Callable = None, penalty_fn: Callable = None
                        ) -> Dict[str, torch.Tensor]:
    """Render B cameras -> image (B, H, W, 3), opacity (B, H, W), depth (B, H, W) (sum w t),
    orient (B, H, W) (sum w max(0, n.d)^2), normal (B, H, W, 3) (sum w n).

    ``training`` jitters the samples and keeps the graph (also through the normals).
    ``normals_fn`` / ``penalty_fn``: see :func:`shaded_field` (required).
    ``chunk`` > 0 renders that many rays per call (evaluation, without a graph). ``estimator``:
    a ``SAMPLERS`` estimator over ``SCENE_BOX`` (None: 'n_samples' stratified samples).
    """
    origins, dirs = camera_rays(cams, normalize=True)
    if light_offset is None:
        light_offset = torch.zeros(3, device=origins.device)
    if normals_fn is None or penalty_fn is None:
        raise TypeError("render_shaded_views needs normals_fn and penalty_fn")
    fn = shaded_field(field, shading, light_offset, ambient, need_normals, create_graph=training,
                      normals_fn=normals_fn, penalty_fn=penalty_fn)
    bg = torch.zeros(N_CHANNELS, device=origins.device)
    bg[:3] = torch.as_tensor(background, dtype=torch.float32, device=origins.device)
    if estimator is None:
        estimator = StratifiedEstimator(n_samples, scene_box=SCENE_BOX)

    def render(o, d):
        out = render_field_rays(fn, o, d, estimator, perturb=training, generator=generator, background=bg,
                                density_field=field)
        return {"color": out["color"], "opacity": out["opacity"], "depth": out["depth"]}

    if chunk > 0:
        out = render_rays_chunked(render, origins, dirs, chunk)
    else:
        flat = render(origins.reshape(-1, 3), dirs.reshape(-1, 3))
        out = {k: v.reshape(*origins.shape[:-1], *v.shape[1:]) for k, v in flat.items()}
    c = out["color"]
    return {"image": c[..., :3], "orient": c[..., 3], "normal": c[..., 4:7], "opacity": out["opacity"],
            "depth": out["depth"]}


def normals_as_latent(out: Dict[str, torch.Tensor]) -> torch.Tensor:
    """(B, 4, H, W) latent from a render: composited normals (3, in [-1, 1]) and 2 opacity - 1."""
    return torch.cat([out["normal"], 2.0 * out["opacity"][..., None] - 1.0], dim=-1).permute(0, 3, 1, 2)


def shading_sampler(probs) -> Callable[[torch.Generator], str]:
    """Draw a shading name with the configured probabilities (normalised; all >= 0)."""
    names = list(probs.keys())
    unknown = [n for n in names if n not in SHADINGS]
    if unknown:
        raise UserError(f"unknown shading '{unknown[0]}' in shading_probs (known: {', '.join(SHADINGS)})")
    p = torch.tensor([float(probs[n]) for n in names])
    if bool((p < 0).any()) or float(p.sum()) <= 0:
        raise UserError(f"shading_probs must be >= 0 with a positive sum, got {dict(probs)}")
    cdf = torch.cumsum(p / p.sum(), 0)

    def draw(generator: torch.Generator) -> str:
        u = float(rand((), generator))
        return names[min(int(torch.searchsorted(cdf, torch.tensor(u))), len(names) - 1)]

    return draw
