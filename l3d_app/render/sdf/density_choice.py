"""``density=auto``: NeuS for a capture seen from below as well as above, VolSDF for one seen from above.

The rule reads only the training cameras: a camera is *below* when its centre lies under the horizontal
plane through the scene box's centre (horizontal: perpendicular to the data's up axis,
:func:`~l3d_app.render.turntable.data_up`), and NeuS is chosen when at least ``below_fraction`` of them are.
On the development scenes (docs/measured/volsdf.md) NeuS halved VolSDF's surface error on ``dev`` (a third
of its cameras below) and VolSDF kept ``ground``'s slab (every camera above) where NeuS raised it.

An ``auto`` config is VolSDF's (conf/density/auto.yaml includes conf/density/volsdf.yaml), so one
transition width drives both densities: NeuS takes ``s = 1 / beta``, ``s_end = 1 / beta_end`` and the
same schedule (``mode``, ``anneal_fraction``).
"""

from __future__ import annotations

from typing import Any, Dict, Mapping, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.render.turntable import data_up

BELOW_FRACTION = 0.25
"""The share of training cameras below the scene from which ``auto`` picks NeuS: half of an all-round
capture's 50 %, set before any run."""


def below_fraction(centres: torch.Tensor, up: torch.Tensor, centre: torch.Tensor) -> float:
    """Fraction in [0, 1] of camera ``centres`` (N, 3) strictly below the plane through ``centre`` (3,)
    perpendicular to ``up`` (3,, any length); 0 for no cameras."""
    if centres.numel() == 0:
        return 0.0
    up = up.to(centres) / up.to(centres).norm()
    return float((((centres - centre.to(centres)) @ up) < 0).double().mean())


def volsdf_config(cfg: Mapping) -> Dict[str, Any]:
    """The ``density=volsdf`` config an ``auto`` config (``cfg``, a mapping) stands for: its own keys."""
    return {**{k: v for k, v in cfg.items() if k != "below_fraction"}, "name": "volsdf"}


def neus_config(cfg: Mapping) -> Dict[str, Any]:
    """The ``density=neus`` config an ``auto`` config stands for: ``s = 1 / beta``, ``s_end = 1 / beta_end``,
    the same schedule mode and fraction (a mode NeuS lacks is refused by :class:`~l3d_app.render.sdf.neus.NeuSDensity`);
    a fixed ``alpha`` (VolSDF's alone) is refused."""
    if cfg.get("alpha") is not None:     # it would hold for one of the two densities only
        raise UserError(f"alpha={cfg['alpha']} is VolSDF's alone, but density=auto may pick NeuS (from the training "
                        f"cameras): use density=volsdf")
    for key in ("beta", "beta_end"):     # VolSDF's own wording (render/sdf/densities.py)
        value = cfg[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise UserError(f"{key} must be > 0 (world units), got {value}")
    return {"name": "neus", "s": 1.0 / cfg["beta"], "mode": str(cfg["mode"]), "s_end": 1.0 / cfg["beta_end"],
            "anneal_fraction": cfg["anneal_fraction"]}


def possible_configs(cfg: Mapping) -> Tuple[Mapping, ...]:
    """Every density config ``cfg`` (``cfg.density``) may become: itself, or for ``auto`` both densities'
    (so that each one's knobs are checked before the data is read)."""
    if str(cfg["name"]) != "auto":
        return (cfg,)
    fraction = cfg.get("below_fraction", BELOW_FRACTION)
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0 < fraction <= 1:
        raise UserError(f"density.below_fraction must lie in (0, 1], got {fraction!r}")
    return volsdf_config(cfg), neus_config(cfg)


def choose_density(cfg: Mapping, data) -> Tuple[Mapping, float]:
    """(the density config to build, the fraction of ``data``'s training cameras below its scene's centre).

    ``cfg`` is ``cfg.density`` (any mapping); anything but ``auto`` comes back unchanged. ``data``: a dataset with
    ``cameras``, ``train`` (indices), ``scene_box`` (2, 3) and optionally ``up``."""
    centres = data.cameras[data.train].centers().detach().to("cpu", torch.float64)
    box = torch.as_tensor(data.scene_box, dtype=torch.float64).cpu()
    fraction = below_fraction(centres, data_up(data).double(), box.mean(dim=0))
    if str(cfg["name"]) != "auto":
        return cfg, fraction
    possible_configs(cfg)
    chosen = (neus_config(cfg) if fraction >= float(cfg.get("below_fraction", BELOW_FRACTION))
              else volsdf_config(cfg))
    return chosen, fraction


def with_density_warmup(optim_cfg: Mapping, density) -> Dict[str, Any]:
    """``optim_cfg`` as a plain dict, a ``warmup_steps`` of ``auto`` made the chosen ``density``'s own learning-rate
    warm-up (``density.warmup_steps``, a module or its class: VolSDF 50 steps, NeuS 150); an integer >= 0 is
    kept, anything else refused."""
    out = {str(k): v for k, v in optim_cfg.items()}
    value = out.get("warmup_steps")
    if value == "auto":
        out["warmup_steps"] = int(density.warmup_steps)
    elif "warmup_steps" in out and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
        raise UserError(f"warmup_steps must be auto or an integer >= 0, got {value!r}")
    return out
