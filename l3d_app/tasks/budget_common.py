"""A preview turntable under a time budget: the frames that still fit, evenly spread, or none.

The field tasks price their gifs with probe frames (:func:`l3d_app.tasks.field_common.write_turntables`);
this is the same rule for the tasks whose gif is one render call over a camera path (fit_point,
fit_mesh, fit_vox, neural_sdf): a gif is a preview no metric reads, so under ``time_budget`` the
training and the test figures come first and the gif takes what is left.
"""

from __future__ import annotations

import time
from typing import Callable, Optional

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.tasks.field_common import turntable_frames_that_fit


def frames_within_budget(ctx, cams: Cameras, render_fn: Callable[[Cameras], torch.Tensor], name: str,
                         least: int = 8) -> Optional[torch.Tensor]:
    """``render_fn(cams)`` -> (N, H, W, C) frames of the N cameras ``cams``; under a time budget
    (``ctx.seconds_left()`` not None) the first frame is rendered and timed alone, then only as many
    frames as fit the seconds left (at least ``least``, else none), evenly spread over the path and
    starting with that first frame. Returns None when no frame fits (a TensorBoard note ``name``
    says so, and says when fewer than N were rendered)."""
    left = ctx.seconds_left()
    n = len(cams)
    if left is None or n == 0:
        return render_fn(cams)
    if left <= 0:
        ctx.logger.text(name, f"time budget {ctx.time_budget:g} s: spent before the gif (not written)")
        return None
    t0 = time.perf_counter()
    first = render_fn(cams[0])
    per_frame = time.perf_counter() - t0
    fit = turntable_frames_that_fit(n, left - per_frame, per_frame, least=least, already=1)
    if fit < n:
        ctx.logger.text(name, f"time budget {ctx.time_budget:g} s: {fit} of {n} gif frames fit the "
                              f"{max(left - per_frame, 0.0):.1f} s left at {per_frame:.2f} s per frame")
    if fit == 0:
        return None
    if fit == 1:
        return first
    idx = (torch.arange(1, fit) * n) // fit                       # evenly spread after frame 0
    rest = render_fn(cams[idx.to(cams.R.device)])
    return torch.cat([first, rest.to(first)], 0)
