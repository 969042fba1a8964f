"""Where a ray first enters an SDF's zero level set, from samples along it (vectorised over rays)."""

from __future__ import annotations

from typing import Callable, Tuple

import torch


def first_crossing(sdf: torch.Tensor, t: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """The first outside-to-inside sign change of ``sdf`` (R, S) at increasing ``t`` (R, S) along each ray.

    Returns ``(t_cross (R,), found (R,) bool)``: ``t`` of the crossing by linear interpolation between the
    two samples that bracket it (``f_i > 0 >= f_{i+1}``); where no pair brackets one, ``found`` is False and
    ``t_cross`` is the ray's first sample. Differentiable in ``sdf`` and ``t``.
    """
    i, frac, found = crossing_bracket(sdf)
    t0, t1 = t.gather(1, i)[:, 0], t.gather(1, i + 1)[:, 0]
    return torch.where(found, t0 + frac * (t1 - t0), t[:, 0]), found


def crossing_bracket(sdf: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where :func:`first_crossing` interpolates: ``(i (R, 1) long, frac (R,), found (R,) bool)``, the
    crossing lying at ``frac`` of the way from sample ``i`` to ``i + 1`` (``i`` 0 where none is found).
    Any per-sample quantity ``q`` (R, S, ...) at the crossing is ``lerp(q[i], q[i + 1], frac)``."""
    outside = sdf > 0
    bracket = outside[:, :-1] & ~outside[:, 1:]
    found = bracket.any(dim=-1)
    i = bracket.to(torch.uint8).argmax(dim=-1, keepdim=True)       # first True (0 where none)
    f0, f1 = sdf.gather(1, i)[:, 0], sdf.gather(1, i + 1)[:, 0]
    frac = (f0 / (f0 - f1).clamp_min(torch.finfo(sdf.dtype).tiny)).clamp(0.0, 1.0)
    return i, frac, found


@torch.no_grad()
def refine_crossing(sdf_fn: Callable[[torch.Tensor], torch.Tensor], origins: torch.Tensor, dirs: torch.Tensor,
                    t_guess: torch.Tensor, half_width: float, n: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """The first crossing of the field ``sdf_fn(points (M, 3)) -> (M,)`` within ``t_guess`` (R,) +- ``half_width``
    (world units), from ``n`` evenly spaced evaluations per ray (no grad): ``(t (R,), found (R,))``, ``t_guess``
    where the window brackets no crossing. ``origins``, ``dirs`` (R, 3)."""
    offsets = torch.linspace(-half_width, half_width, n, dtype=t_guess.dtype, device=t_guess.device)
    t = t_guess[:, None] + offsets                                             # (R, n)
    f = sdf_fn((origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(-1, 3)).reshape(t.shape)
    t_cross, found = first_crossing(f, t)
    return torch.where(found, t_cross, t_guess), found
