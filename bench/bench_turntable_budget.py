"""Benchmark: how well :func:`l3d_app.render.previews.write_turntables` prices a finished run's
turntable under a time budget. Re-renders the colour | depth turntable of a train_nerf, volsdf or
gs_train run directory (its checkpoint, :func:`l3d_app.pipelines.runs.run_renderer`) with ``--left``
seconds left on a clock that starts at ``time_budget - left``, and prints the frames the probe chose, its price per
frame and the seconds the turntable took (probe included): within ``--left`` when the price holds.
Also the cost of each orbit frame rendered alone against the probe's frame 0 (``--per-frame``).
Run by hand, never in tests:

    python bench/bench_turntable_budget.py RUN_DIR [--left 22] [--threads 2] [--per-frame]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing


def main() -> None:
    from omegaconf import OmegaConf

    from l3d_app.pipelines.runs import run_renderer
    from l3d_app.render.evaluation import panel_frames
    from l3d_app.render.previews import write_turntables
    from l3d_app.render.turntable import data_orbit
    from l3d_app.runtime.budget import TimeBudget
    from l3d_app.runtime.checkpoints import read_checkpoint

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a finished train_nerf / volsdf / gs_train run directory")
    ap.add_argument("--left", type=float, default=22.0, help="seconds left in the budget when the turntable starts")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--per-frame", action="store_true", help="also time every orbit frame alone")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    conf = OmegaConf.to_container(OmegaConf.load(Path(args.run) / ".hydra" / "config.yaml"), resolve=True)
    seconds, frames = float(conf.get("time_budget", 590) or 590), int(conf.get("gif_frames", 36) or 36)
    render, data, kind = run_renderer(conf, read_checkpoint(Path(args.run) / "checkpoint.pt")["trainable"], "cpu",
                                      int(conf.get("chunk", 8192)))
    width = int(conf.get("turntable_size", 0) or 0) or min(data.cameras.width, int(conf.get("turntable_max", 0) or 0)
                                                           or data.cameras.width)
    orbit = lambda n: data_orbit(data, n, float(conf.get("gif_elevation", 30)), width, "cpu")  # noqa: E731
    frames_fn = lambda cams: panel_frames(render(cams), ["color", "depth"])  # noqa: E731
    with torch.no_grad():
        if args.per_frame:
            cams = orbit(frames)
            frames_fn(cams[0])                                          # warm-up
            costs = []
            for i in range(len(cams)):
                t0 = time.perf_counter()
                frames_fn(cams[i])
                costs.append(time.perf_counter() - t0)
            c = torch.tensor(costs)
            print(f"{kind}: {len(costs)} orbit frames alone: frame 0 {costs[0]:.3f} s, mean {c.mean():.3f} s, "
                  f"max {c.max():.3f} s (mean / frame 0 = {c.mean() / costs[0]:.3f})")
        notes = []
        start = time.perf_counter() - (seconds - args.left)           # the clock reads seconds - left now
        budget = TimeBudget(seconds, clock=lambda: time.perf_counter() - start,
                            note=lambda tag, text: notes.append(text))
        with tempfile.TemporaryDirectory() as out:       # the gif is written, then thrown away
            t0 = time.perf_counter()
            written = write_turntables({Path(out) / "render.gif": frames_fn}, orbit, frames,
                                       float(conf.get("fps", 12)), budget)
            took = time.perf_counter() - t0
    print(f"{kind}: {args.left:g} s left: {written} of {frames} frames written in {took:.2f} s "
          f"({'within' if took <= args.left else 'OVER'} the time left){'; ' + notes[0] if notes else ''}")


if __name__ == "__main__":
    main()
