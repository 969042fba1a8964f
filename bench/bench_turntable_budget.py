"""Benchmark: how well :func:`l3d_app.tasks.field_common.write_turntables` prices a finished run's
turntable under a time budget. Re-renders the colour | depth turntable of a train_nerf, volsdf or
gs_train run directory (its checkpoint, ``render_path``'s loader) with ``--left`` seconds left on a
stopwatch that starts at ``time_budget - left``, and prints the frames the probe chose, its price per
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
from types import SimpleNamespace

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing


class _Stopwatch:
    """A task stopwatch that reads ``start`` seconds at construction and runs with the wall clock."""

    def __init__(self, start: float):
        self.start, self.t0 = float(start), time.perf_counter()

    @property
    def elapsed(self) -> float:
        return self.start + time.perf_counter() - self.t0


def main() -> None:
    from omegaconf import OmegaConf

    from l3d_app.tasks.field_common import turntable_orbit, write_turntables
    from l3d_app.tasks.render_path import load_run, panel_frames

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a finished train_nerf / volsdf / gs_train run directory")
    ap.add_argument("--left", type=float, default=22.0, help="seconds left in the budget when the turntable starts")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--per-frame", action="store_true", help="also time every orbit frame alone")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    conf = OmegaConf.load(Path(args.run) / ".hydra" / "config.yaml")
    budget = float(conf.get("time_budget", 590) or 590)
    cfg = OmegaConf.create({"gif_frames": int(conf.get("gif_frames", 36) or 36), "time_budget": budget,
                            "fps": float(conf.get("fps", 12)), "gif_elevation": float(conf.get("gif_elevation", 30)),
                            "turntable_size": int(conf.get("turntable_size", 0) or 0),
                            "turntable_max": int(conf.get("turntable_max", 0) or 0)})
    render, data, kind = load_run(args.run, "cpu", int(conf.get("chunk", 8192)))
    frames_fn = lambda cams: panel_frames(render(cams), ["color", "depth"])  # noqa: E731
    with torch.no_grad():
        if args.per_frame:
            cams = turntable_orbit(cfg, data, int(cfg.gif_frames), "cpu")
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
        with tempfile.TemporaryDirectory() as out:       # the gif is written, then thrown away
            ctx = SimpleNamespace(stopwatch=_Stopwatch(budget - args.left), device="cpu",
                                  path=lambda name: Path(out) / name,
                                  logger=SimpleNamespace(text=lambda tag, value: notes.append(value)))
            t0 = time.perf_counter()
            written = write_turntables(cfg, ctx, data, {"render.gif": frames_fn})
            took = time.perf_counter() - t0
    print(f"{kind}: {args.left:g} s left: {written} of {int(cfg.gif_frames)} frames written in {took:.2f} s "
          f"({'within' if took <= args.left else 'OVER'} the time left){'; ' + notes[0] if notes else ''}")


if __name__ == "__main__":
    main()
