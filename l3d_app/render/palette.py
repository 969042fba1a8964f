"""Colours for labels and errors: distinct label colours and a blue -> red error ramp."""

from __future__ import annotations

import numpy as np
import torch

from l3d_app.errors import UserError


def palette(n: int) -> torch.Tensor:
    """(n, 3) distinct RGB colours in [0, 1] (matplotlib tab10 / tab20 / hsv)."""
    import matplotlib

    if int(n) < 1:
        raise ValueError(f"palette needs n >= 1, got {n}")
    name = "tab10" if n <= 10 else "tab20" if n <= 20 else "hsv"
    cmap = matplotlib.colormaps[name]
    x = np.arange(n) if name != "hsv" else np.linspace(0, 1, n, endpoint=False)
    return torch.tensor(np.asarray(cmap(x))[:, :3], dtype=torch.float32)


def error_colors(errors: torch.Tensor, max_error: float) -> torch.Tensor:
    """(P, 3) colours of (P,) non-negative errors: blue at 0 -> red at >= ``max_error``
    (matplotlib's coolwarm)."""
    import matplotlib

    if not max_error > 0:
        raise UserError(f"max_error must be > 0, got {max_error}")
    x = (errors.detach().float().cpu() / float(max_error)).clamp(0, 1).numpy()
    return torch.from_numpy(matplotlib.colormaps["coolwarm"](x)[:, :3]).float().reshape(-1, 3)
