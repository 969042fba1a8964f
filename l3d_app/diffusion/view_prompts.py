"""View-dependent prompting for text-to-3D (DreamFusion): random orbit views and the
prompt embedding each view should be guided by.

Views are named by where the camera sits (world +Y up, ``look_at`` placement: azimuth 0
is the camera on +Z, the object's *front*; azimuth grows towards +X):

* ``overhead`` when the elevation is above ``+overhead_deg``, ``bottom`` below ``-overhead_deg``;
* otherwise ``front`` / ``side`` / ``back`` blended by the azimuth's distance from the
  front, ``a = |wrap(azimuth)|`` in [0, 180] degrees: ``front = 1 - a/90``, ``side = a/90``
  for ``a <= 90``; ``side = (180 - a)/90``, ``back = (a - 90)/90`` beyond. The weights are
  non-negative, sum to 1, pick ``front`` at 0 degrees, ``side`` at +-90 and ``back`` at 180.

The blended embedding is the weighted sum of the per-view prompt embeddings (linear
interpolation of the conditioning, as in Stable-DreamFusion); the unconditional embedding
is shared.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Mapping, Optional, Sequence, Tuple

import torch

from l3d_app.diffusion.prior import DiffusionPrior, PromptEmbedding
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, look_at_cameras
from l3d_app.runtime.config_values import config_floats

VIEWS = ("front", "side", "back", "overhead", "bottom")
DEFAULT_TEMPLATE = "{prompt}, {view} view"


def view_weights(azimuth_deg: torch.Tensor, elevation_deg: torch.Tensor,
                 overhead_deg: float = 60.0) -> torch.Tensor:
    """(B, 5) blending weights over :data:`VIEWS` for cameras at (azimuth, elevation) degrees (B,)."""
    azim = torch.as_tensor(azimuth_deg, dtype=torch.float32).reshape(-1)
    elev = torch.as_tensor(elevation_deg, dtype=torch.float32, device=azim.device).reshape(-1)
    a = torch.remainder(azim + 180.0, 360.0) - 180.0           # (-180, 180]
    a = a.abs().clamp(0.0, 180.0)
    front = (1.0 - a / 90.0).clamp_min(0.0)
    back = (a / 90.0 - 1.0).clamp_min(0.0)
    side = 1.0 - front - back
    w = torch.stack([front, side, back, torch.zeros_like(a), torch.zeros_like(a)], dim=-1)
    top, bottom = elev > overhead_deg, elev < -overhead_deg
    w = torch.where((top | bottom)[:, None], torch.zeros_like(w), w)
    w[:, 3] = top.float()
    w[:, 4] = bottom.float()
    return w


def view_names(azimuth_deg: torch.Tensor, elevation_deg: torch.Tensor, overhead_deg: float = 60.0) -> list:
    """The dominant view name of each camera (for logging)."""
    return [VIEWS[i] for i in view_weights(azimuth_deg, elevation_deg, overhead_deg).argmax(-1).tolist()]


@dataclass
class ViewPrompts:
    """Embeddings of one prompt per view, blended per camera by :func:`view_weights`.

    ``cond``: (5, ...) the per-view conditional embeddings (VIEWS order); ``uncond``: (1, ...).
    """

    cond: torch.Tensor
    uncond: torch.Tensor
    prompts: Tuple[str, ...]
    overhead_deg: float = 60.0

    @classmethod
    def build(cls, prior: DiffusionPrior, prompt: str, view_dependent: bool = True,
              template: str = DEFAULT_TEMPLATE, overrides: Optional[Mapping[str, str]] = None,
              overhead_deg: float = 60.0) -> "ViewPrompts":
        """Embed the five view prompts of ``prompt``.

        With ``view_dependent`` each view's prompt is ``template`` filled with the prompt
        and the view name; without it every view uses ``prompt`` itself. ``overrides``
        replace whole view prompts by name (e.g. ``{"overhead": "a red circle"}``).
        """
        overrides = dict(overrides or {})
        unknown = sorted(set(overrides) - set(VIEWS))
        if unknown:
            raise UserError(f"unknown view '{unknown[0]}' in view prompts (known: {', '.join(VIEWS)})")
        if view_dependent and ("{prompt}" not in template or "{view}" not in template):
            raise UserError(f"view prompt template must contain {{prompt}} and {{view}}, got {template!r}")
        prompts = tuple(overrides.get(v, template.format(prompt=prompt, view=v) if view_dependent else prompt)
                        for v in VIEWS)
        cache: Dict[str, PromptEmbedding] = {}
        for p in prompts:
            if p not in cache:
                cache[p] = prior.embed_prompt(p)
        cond = torch.cat([cache[p].cond for p in prompts], dim=0)
        return cls(cond=cond, uncond=cache[prompts[0]].uncond, prompts=prompts, overhead_deg=float(overhead_deg))

    def weights(self, azimuth_deg: torch.Tensor, elevation_deg: torch.Tensor) -> torch.Tensor:
        return view_weights(azimuth_deg, elevation_deg, self.overhead_deg)

    def embedding(self, azimuth_deg: torch.Tensor, elevation_deg: torch.Tensor) -> PromptEmbedding:
        """The blended embedding of B cameras: cond (B, ...), uncond (1, ...)."""
        w = self.weights(azimuth_deg, elevation_deg).to(self.cond.device, self.cond.dtype)
        cond = torch.einsum("bv,v...->b...", w, self.cond)
        return PromptEmbedding(cond=cond, uncond=self.uncond)


def check_orbit_ranges(distance: Sequence[float] = (3.0, 3.0), elevation: Sequence[float] = (-10.0, 60.0),
                       azimuth: Sequence[float] = (0.0, 360.0), fov: Sequence[float] = (40.0, 40.0)
                       ) -> Tuple[Tuple[float, float], ...]:
    """The (lo, hi) ranges of :func:`sample_orbit_cameras` as float pairs, or :class:`UserError`:
    each two numbers with lo <= hi, distances > 0, fields of view in (0, 180) degrees,
    elevations strictly inside (-90, 90) degrees. Tasks call it before any work."""
    pairs = []
    for lo_hi, name in ((distance, "distance"), (elevation, "elevation"), (azimuth, "azimuth"), (fov, "fov")):
        lo, hi = config_floats(lo_hi, f"{name} range [lo, hi]", 2)
        if hi < lo:
            raise UserError(f"{name} range must be [lo, hi] with lo <= hi, got {[lo, hi]}")
        pairs.append((lo, hi))
    (d_lo, _), (e_lo, e_hi), _, (f_lo, f_hi) = pairs
    if d_lo <= 0 or not (0 < f_lo and f_hi < 180):
        raise UserError("camera distances must be > 0 and fields of view in (0, 180) degrees")
    if max(abs(e_lo), abs(e_hi)) >= 90:
        raise UserError("camera elevations must lie strictly inside (-90, 90) degrees")
    return tuple(pairs)


def sample_orbit_cameras(n: int, image_size: int, generator: torch.Generator,
                         distance: Sequence[float] = (3.0, 3.0), elevation: Sequence[float] = (-10.0, 60.0),
                         azimuth: Sequence[float] = (0.0, 360.0), fov: Sequence[float] = (40.0, 40.0),
                         device=None) -> Tuple[Cameras, torch.Tensor, torch.Tensor]:
    """``n`` cameras looking at the origin, each range (lo, hi) sampled uniformly
    (checked by :func:`check_orbit_ranges`).

    distance in world units, angles in degrees. Returns (cameras, azimuth (n,), elevation (n,)).
    """
    def draw(lo_hi):
        lo, hi = lo_hi
        u = torch.rand(n, generator=generator, device=generator.device).cpu()
        return lo + (hi - lo) * u

    dist, elev, azim, fovs = (draw(r) for r in check_orbit_ranges(distance, elevation, azimuth, fov))
    cams = look_at_cameras(dist, elev, azim, fovs, int(image_size), device=None)
    return cams.to(device), azim, elev
