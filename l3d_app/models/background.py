"""What lies behind the scene box: one RGB composited behind every ray or splat, learnt or fixed."""

from __future__ import annotations

import torch

from l3d_app.errors import UserError


def background_parameter(mode, data) -> torch.nn.ParameterDict:
    """What lies behind the scene box: one RGB composited behind every ray or splat.

    Args:
        mode: ``learn_background`` knob: ``auto`` (learn when ``data.background_known`` is
            False, i.e. a real capture), ``true`` or ``false``.
        data: a multi-view dataset with ``background`` (3,) in [0, 1] (the loader's estimate
            when not known).
    Returns:
        ``ParameterDict`` with ``"rgb"`` (3,), starting at ``data.background``; it requires
        grad only when learnt (callers clamp it to [0, 1] when rendering and pass it to the
        optimiser only when ``requires_grad``).
    """
    key = str(mode).lower()
    choices = {"auto": not getattr(data, "background_known", True), "true": True, "false": False}
    if key not in choices:
        raise UserError(f"learn_background must be auto, true or false, got {mode!r}")
    rgb = torch.nn.Parameter(data.background.clone().float(), requires_grad=choices[key])
    return torch.nn.ParameterDict({"rgb": rgb})
