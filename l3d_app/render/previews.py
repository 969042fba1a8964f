"""Preview gifs under a time budget: the frames that still fit, evenly spread, or none.

A turntable is a preview no metric reads: under a time budget the training and the test figures
come first and the gifs take what is left. Frames are priced by rendering some of them first, on
the budget's clock (:class:`~l3d_app.runtime.budget.TimeBudget`), and only as many as fit the
seconds left are written (:func:`~l3d_app.runtime.budget.frames_that_fit`):

* :func:`write_turntables` (the field tasks): p = gcd(frames, 4) evenly spread probe frames of each
  gif (azimuths 0, 90, 180, 270 degrees for a multiple of 4: a frame's cost varies along an orbit)
  are rendered and GIF-encoded in memory (encoding is part of a frame's cost), then a multiple of
  p frames is written, reusing the probe's;
* :func:`frames_within_budget` (a gif that is one render call over a camera path): the first
  frame is rendered alone and timed, then as many more as fit, spread over the path.
"""

from __future__ import annotations

import math
from typing import Callable, Dict, Optional

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.render.turntable import write_turntable
from l3d_app.runtime.budget import TimeBudget, frames_that_fit
from l3d_app.runtime.media import gif_bytes

FramesFn = Callable[[Cameras], torch.Tensor]


@torch.no_grad()
def write_turntables(gifs: Dict[str, FramesFn], orbit: Callable[[int], Cameras], frames: int, fps: float,
                     budget: TimeBudget) -> int:
    """Write each ``gifs`` entry (path -> ``frames_fn(cameras) -> (N, H, W, 3)``) as a turntable of
    ``frames`` frames on the cameras ``orbit(n)``; under ``budget`` only the frames that fit (a
    TensorBoard note ``gifs`` says when fewer), none (not even the probe) once the budget is spent,
    and none after probe frame 0 when fewer than 8 frames at its cost fit. Returns the frames
    written per gif."""
    asked, probed = max(int(frames), 0), {}
    frames = asked
    left = budget.seconds_left()
    if asked > 0 and left is not None and left <= 0:     # nothing left: no probe either
        budget.note("gifs", f"time budget {budget.seconds:g} s: spent before the turntables (no gif)")
        return 0
    if asked > 0 and left is not None:
        p = math.gcd(asked, 4)
        probe = orbit(p)
        t0 = budget.clock()
        probed = {name: frames_fn(probe[0]) for name, frames_fn in gifs.items()}       # probe frame 0 first
        first, least = budget.clock() - t0, min(8, asked)
        if budget.seconds_left() < (least - 1) * first:       # the least gif does not fit: stop here
            budget.note("gifs", f"time budget {budget.seconds:g} s: {max(budget.seconds_left(), 0.0):.1f} s left at "
                                f"{first:.2f} s per frame (probe frame 0): fewer than {least} turntable frames fit (no gif)")
            return 0
        if p > 1:
            probed = {name: torch.cat([shots, gifs[name](probe[1:]).to(shots)], 0) for name, shots in probed.items()}
        t1 = budget.clock()
        for shots in probed.values():
            gif_bytes(shots.clamp(0, 1), fps)
        t2 = budget.clock()
        per_frame = (t2 - t0) / p
        left = budget.seconds_left() - (t2 - t1)     # the probe frames are encoded again in the gifs
        frames = frames_that_fit(asked, left, per_frame, already=p, multiple=p)
        if frames < asked:
            budget.note("gifs", f"time budget {budget.seconds:g} s: {frames} of {asked} turntable frames fit the "
                                f"{max(left, 0.0):.1f} s left at {per_frame:.2f} s per frame "
                                f"({'no gif' if frames == 0 else 'fewer frames'})")
    if frames > 0:
        cams = orbit(frames)
        for path, frames_fn in gifs.items():
            write_turntable(path, reuse_probe_frames(frames_fn, probed.get(path)), cams, fps)
    return frames


def reuse_probe_frames(frames_fn: FramesFn, probed: Optional[torch.Tensor]) -> FramesFn:
    """``frames_fn`` for an orbit of N cameras whose frames 0, N/p, 2N/p, ... are the p ``probed`` frames
    (p, H, W, 3) already rendered (the same azimuths: N a multiple of p): renders only the other N - p."""
    if probed is None:
        return frames_fn

    def frames(cams: Cameras) -> torch.Tensor:
        n, p = len(cams), len(probed)
        if n % p:
            raise ValueError(f"an orbit of {n} frames does not hold {p} evenly spread probe frames")
        if n == p:
            return probed
        rest = (torch.arange(n, device=cams.R.device) % (n // p)) != 0
        shots = frames_fn(cams[rest.nonzero()[:, 0]])
        out = shots.new_empty((n,) + tuple(shots.shape[1:]))
        out[rest.to(out.device)] = shots
        out[~rest.to(out.device)] = probed.to(out)
        return out
    return frames


def frames_within_budget(budget: TimeBudget, cams: Cameras, render_fn: FramesFn, name: str,
                         least: int = 8) -> Optional[torch.Tensor]:
    """``render_fn(cams)`` -> (N, H, W, C) frames of the N cameras ``cams``; under ``budget`` the first
    frame is rendered and timed alone, then only as many frames as fit the seconds left (at least
    ``least``, else none), evenly spread over the path and starting with that first frame. Returns
    None when no frame fits (a TensorBoard note ``name`` says so, and says when fewer than N were
    rendered)."""
    left = budget.seconds_left()
    n = len(cams)
    if left is None or n == 0:
        return render_fn(cams)
    if left <= 0:
        budget.note(name, f"time budget {budget.seconds:g} s: spent before the gif (not written)")
        return None
    t0 = budget.clock()
    first = render_fn(cams[0])
    per_frame = budget.clock() - t0
    fit = frames_that_fit(n, left - per_frame, per_frame, least=least, already=1)
    if fit < n:
        budget.note(name, f"time budget {budget.seconds:g} s: {fit} of {n} gif frames fit the "
                          f"{max(left - per_frame, 0.0):.1f} s left at {per_frame:.2f} s per frame")
    if fit == 0:
        return None
    if fit == 1:
        return first
    idx = (torch.arange(1, fit) * n) // fit                       # evenly spread after frame 0
    rest = render_fn(cams[idx.to(cams.R.device)])
    return torch.cat([first, rest.to(first)], 0)
