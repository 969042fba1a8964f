"""Shared wiring of the field tasks (train_nerf, volsdf): one evaluation of a set of views."""

from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.metrics.image import psnr, ssim
from l3d_app.render.evaluation import RenderFn, evaluation_picture, render_views
from l3d_app.render.field_mesh import priced_mesh_seconds
from l3d_app.render.mesh.visibility import cull_unseen_faces
from l3d_app.runtime.media import save_png


@torch.no_grad()
def evaluate_views(render_fn: RenderFn, cameras: Cameras, images: torch.Tensor, chunk: int = 8192,
                   supersample: int = 1, max_picture_views: int = 4
                   ) -> Tuple[Dict[str, float], torch.Tensor, Dict[str, torch.Tensor]]:
    """Render ``cameras`` and score them against ``images`` (V, H, W, 3) in [0, 1].

    Returns ({"psnr": dB, "ssim": ...} over all views, the ``pred | truth | error | depth``
    picture of the first ``max_picture_views`` views, the renders).
    """
    out = render_views(render_fn, cameras, chunk, supersample)
    pred = out["color"].clamp(0, 1)
    metrics = {"psnr": float(psnr(pred, images)), "ssim": float(ssim(pred, images))}
    picture = evaluation_picture(pred, images, out.get("depth"), out.get("opacity"), max_picture_views)
    return metrics, picture, out


class BeforeAfter:
    """The validation picture before training and at the last evaluation, side by side.

    ``before(evaluate_fn)`` renders the val views once before the first step (no sampler
    update, no random draw: the run's stream is untouched) and logs ``val/before_training``;
    ``after(picture)`` keeps each evaluation's picture; ``save(ctx)`` writes
    ``before_after.png`` (before above, last evaluation below) and returns ``{"before_val_psnr"}``.
    A task checkpoints it with the run (``Trainable.extra``), so a resumed run keeps both.
    """

    def __init__(self):
        self.pictures: Dict[str, torch.Tensor] = {}
        self.before_psnr = float("nan")

    def before(self, ctx, evaluate_fn) -> None:
        with torch.no_grad():
            metrics, self.pictures["before"], _ = evaluate_fn()
        self.before_psnr = float(metrics["psnr"])
        ctx.logger.image("val/before_training", self.pictures["before"], 0)

    def after(self, picture: torch.Tensor) -> None:
        self.pictures["last"] = picture

    def state_dict(self) -> Dict[str, object]:
        return {"pictures": dict(self.pictures), "before_psnr": self.before_psnr}

    def load_state_dict(self, state: Dict[str, object]) -> None:
        self.pictures = dict(state["pictures"])
        self.before_psnr = float(state["before_psnr"])

    def save(self, ctx) -> Dict[str, float]:
        if {"before", "last"} <= set(self.pictures):
            save_png(ctx.path("before_after.png"), torch.cat([self.pictures["before"], self.pictures["last"]], 0))
            return {"before_val_psnr": round(self.before_psnr, 4)}
        return {}


def turntable_width(cfg, data_width: int) -> int:
    """Turntable frame width in pixels: ``cfg.turntable_size`` when set, else the data's
    ``data_width`` capped at ``cfg.turntable_max`` (a task's optional key; 0 or absent: no cap).
    The cap keeps a preview of 256-800 px data from costing more than the test views."""
    size = int(cfg.turntable_size)
    if size:
        return size
    cap = int(cfg.get("turntable_max", 0) or 0)
    return min(int(data_width), cap) if cap > 0 else int(data_width)


def turntable_frames_that_fit(frames: int, seconds_left: Optional[float], seconds_per_frame: float,
                              least: int = 8, already: int = 0, multiple: int = 1) -> int:
    """How many of ``frames`` turntable frames a run renders at its end: all of them without a
    time budget (``seconds_left`` None), else the ``already`` rendered ones plus as many as fit
    ``seconds_left`` at ``seconds_per_frame`` (one frame of every turntable the task writes), rounded
    down to a ``multiple``; 0 (no gif) when fewer than ``least`` fit (or fewer than ``frames`` when
    that is smaller): a turntable is a preview no metric reads, so under a budget the training steps
    come first and the gifs take what is left (``evals_after_training`` leaves them out of the loop's
    reserve)."""
    frames = int(frames)
    if seconds_left is None or frames <= 0:
        return max(frames, 0)
    per_frame = max(float(seconds_per_frame), 0.0)
    fit = frames if per_frame <= 0 else int(already) + int(max(float(seconds_left), 0.0) // per_frame)
    fit = min(frames, fit)
    fit -= fit % max(int(multiple), 1)
    return fit if fit >= min(int(least), frames) else 0


def turntable_orbit(cfg, data, frames: int, device) -> Cameras:
    """``frames`` cameras orbiting the data's up axis at the cameras' mean distance, ``cfg.gif_elevation``
    degrees, the data's field of view, :func:`turntable_width` px."""
    from l3d_app.render.turntable import data_up, orbit_cameras
    return orbit_cameras(int(frames), float(data.cameras.centers().norm(dim=-1).mean()), float(cfg.gif_elevation),
                         float(data.cameras.fov()[0]), turntable_width(cfg, data.cameras.width), up=data_up(data),
                         device=device)


@torch.no_grad()
def write_turntables(cfg, ctx, data, gifs: Dict[str, Callable[[Cameras], torch.Tensor]]) -> int:
    """Write each ``gifs`` entry (file name -> ``frames_fn(cameras) -> (N, H, W, 3)``) as a turntable of
    ``cfg.gif_frames`` frames. With ``cfg.time_budget`` > 0 the frames are priced first: p = gcd(frames, 4)
    evenly spread probe frames of each gif (azimuths 0, 90, 180, 270 degrees for a multiple of 4: a
    frame's cost varies along an orbit and between calls: frame 0 alone priced the held-out ``around``
    run's two gifs at 1.10 s a frame where they cost 1.25) are rendered and
    GIF-encoded in memory (encoding is part of a frame's cost), timed; then only the frames that fit the
    time left are written (:func:`turntable_frames_that_fit`, a multiple of p, so every orbit holds the
    probe's azimuths and reuses its frames; a TensorBoard note ``gifs`` says when fewer). Rendered
    without autograd; none (not even the probe) once the budget is spent, and none after probe frame 0
    when fewer than 8 frames at its cost fit. Returns the frames written per gif."""
    import math
    import time

    from l3d_app.render.turntable import write_turntable
    from l3d_app.runtime.media import gif_bytes
    asked, budget, fps = int(cfg.gif_frames), float(cfg.time_budget), float(cfg.fps)
    frames, probed = max(asked, 0), {}
    if asked > 0 and budget > 0 and budget - ctx.stopwatch.elapsed <= 0:     # nothing left: no probe either
        ctx.logger.text("gifs", f"time budget {budget:g} s: spent before the turntables (no gif)")
        return 0
    if asked > 0 and budget > 0:
        p = math.gcd(asked, 4)
        probe = turntable_orbit(cfg, data, p, ctx.device)
        t0 = time.perf_counter()
        probed = {name: frames_fn(probe[0]) for name, frames_fn in gifs.items()}       # probe frame 0 first
        first, least = time.perf_counter() - t0, min(8, asked)
        if budget - ctx.stopwatch.elapsed < (least - 1) * first:       # the least gif does not fit: stop here
            ctx.logger.text("gifs", f"time budget {budget:g} s: {max(budget - ctx.stopwatch.elapsed, 0.0):.1f} s "
                                    f"left at {first:.2f} s per frame (probe frame 0): fewer than {least} "
                                    "turntable frames fit (no gif)")
            return 0
        if p > 1:
            probed = {name: torch.cat([shots, gifs[name](probe[1:]).to(shots)], 0) for name, shots in probed.items()}
        t1 = time.perf_counter()
        for shots in probed.values():
            gif_bytes(shots.clamp(0, 1), fps)
        t2 = time.perf_counter()
        per_frame = (t2 - t0) / p
        left = budget - ctx.stopwatch.elapsed - (t2 - t1)     # the probe frames are encoded again in the gifs
        frames = turntable_frames_that_fit(asked, left, per_frame, already=p, multiple=p)
        if frames < asked:
            ctx.logger.text("gifs", f"time budget {budget:g} s: {frames} of {asked} turntable frames fit the "
                                    f"{max(left, 0.0):.1f} s left at {per_frame:.2f} s per frame "
                                    f"({'no gif' if frames == 0 else 'fewer frames'})")
    if frames > 0:
        cams = turntable_orbit(cfg, data, frames, ctx.device)
        for name, frames_fn in gifs.items():
            write_turntable(ctx.path(name), reuse_probe_frames(frames_fn, probed.get(name)), cams, fps)
    return frames


def reuse_probe_frames(frames_fn: Callable[[Cameras], torch.Tensor], probed: Optional[torch.Tensor]
                       ) -> Callable[[Cameras], torch.Tensor]:
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


def evals_after_training(n_eval_views: int, n_test_views: int, supersample: int = 1,
                         val_supersample: Optional[int] = None) -> float:
    """The rendering a field task keeps time for after its training loop (the test views at
    ``supersample``^2 rays per pixel; the turntables are not kept for:
    :func:`write_turntables` gives them what is left), in units of one validation evaluation
    (``n_eval_views`` views of the same size at ``val_supersample``^2 rays per pixel; None:
    ``supersample``); the loop turns it into seconds with its own timing (``train(reserve_evals=...)``)."""
    val_ss = supersample if val_supersample is None else int(val_supersample)
    return n_test_views * supersample ** 2 / max(1, n_eval_views * val_ss ** 2)


def mesh_seconds_to_keep(cfg, ctx, knob: str, level_fn: Callable[[torch.Tensor], torch.Tensor], box) -> float:
    """Seconds a field task keeps under ``cfg.time_budget`` for its marching-cubes mesh: ``cfg[knob]``
    (its price at ``mesh_resolution`` 128) or, at another resolution,
    :func:`~l3d_app.render.field_mesh.priced_mesh_seconds` with ``level_fn`` ((N, 3) -> (N,)) timed over
    ``box``; a TensorBoard note ``reserve`` gives the measured cost."""
    resolution = int(cfg.mesh_resolution)
    seconds, per_point = priced_mesh_seconds(resolution, float(cfg[knob]), level_fn, box, float(cfg.time_budget),
                                             ctx.device)
    if per_point is not None:
        ctx.logger.text("reserve", f"{seconds:.1f} s kept for the mesh at mesh_resolution={resolution} ({knob}="
                                   f"{float(cfg[knob]):g} s at 128; the field costs {1e6 * per_point:.2f} us per "
                                   f"grid point, measured)")
    return seconds


def cull_to_training_views(mesh: Mesh, data, box, resolution: int) -> Tuple[Mesh, float]:
    """The extracted ``mesh`` without the faces no TRAINING camera sees (the leftover of the
    initialisation below a plate seen from above, surfaces inside objects) and the share of
    its area removed. The depth tolerance is two marching-cubes cells of the ``box``
    ((2, 3) or nested lists) at ``resolution``: the grid's own precision, not a tuned value."""
    lo, hi = torch.as_tensor(box, dtype=torch.float64)
    tolerance = 2.0 * float((hi - lo).max()) / int(resolution)
    cams = data.cameras[data.train.to(data.cameras.device)]
    return cull_unseen_faces(mesh, cams, tolerance)

