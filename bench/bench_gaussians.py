"""Benchmark: Gaussian rasteriser forward+backward on one truck view, and gs_train on the
truck against wall time. Run by hand, never in tests:

    python bench/bench_gaussians.py [--threads 2] [--repeats 20] [--tile 4]
                                    [--short | --no-train] [--state CHECKPOINT]

Part 1: 10k Gaussians initialised from points_10000.npy (isotropic scales = mean distance
to the 3 nearest neighbours, opacity 0.1, SH degree 3), one 160x90 training view; median
and min of ``--repeats`` fwd+bwd (L1 loss), the median CPU time of the process (with
``--threads 1`` on a loaded machine, close to the wall time on a quiet one), peak RSS of
the process and the number of (splat, tile) overlaps. ``--state`` takes a
gs_train ``checkpoint.pt`` instead (a trained, densified model).
Part 2: ONE ``gs_train data=truck`` run through main.py for 600 s of training (``--short``:
180 s), evaluated every 50 steps; prints test PSNR / SSIM / Gaussian count / steps reached
at 1, 3 and 10 minutes of wall time (the last evaluation at or before each mark; wall time
counts everything from the task's start, data loading and evaluations included).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from l3d_app.data.nerf_formats import truck  # noqa: E402
from l3d_app.models.gaussians import init_from_points  # noqa: E402
from l3d_app.render.gaussians import rasterize_gaussians  # noqa: E402


def bench_raster(args) -> dict:
    root = REPO.parent / "shared" / "data" / "truck"
    data = truck(root=str(root))
    pts = torch.from_numpy(np.load(root / "points" / "points_10000.npy").astype(np.float32))
    model = init_from_points(pts, None, sh_degree=3, opacity=0.1)
    if args.state:
        model.load_state_dict(torch.load(args.state, weights_only=False)["trainable"]["modules"]["gaussians"])
    params = [p.detach().clone().requires_grad_(True) for p in
              (model.means, model.log_scales, model.quats, model.opacity_logits, model.sh)]
    cam = data.cameras[int(data.train[0])]
    target = data.images[int(data.train[0])]
    times, cpu = [], []
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    n_pairs = 0
    for i in range(args.repeats + 2):
        t0, c0 = time.perf_counter(), time.process_time()
        out = rasterize_gaussians(*params, 3, cam, data.background, tile_size=args.tile)
        loss = (out["color"][0] - target).abs().mean()
        loss.backward()
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        for p in params:
            p.grad = None
        n_pairs = int(out["n_pairs"].sum())
        if i >= 2:
            times.append(dt)
            cpu.append(dc)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # CPU seconds of this process: on a loaded machine with --threads 1 this is close to what
    # the wall time would be on a quiet one (the wall time also counts waiting for a core)
    res = {"fwd_bwd_median_s": statistics.median(times), "fwd_bwd_min_s": min(times),
           "fwd_bwd_cpu_median_s": statistics.median(cpu),
           "peak_rss_mb": rss / 1024, "rss_growth_mb": (rss - rss0) / 1024, "n_tile_overlaps": n_pairs, "n_gaussians": model.num,
           "threads": torch.get_num_threads(), "tile": args.tile}
    return res


def bench_train(budget: float, marks, threads: int, out: Path) -> dict:
    run_dir = out / f"truck_{int(budget)}s"
    cmd = [sys.executable, str(REPO / "main.py"), "task=gs_train", "data=truck", "iters=1000000",
           f"time_budget={budget}", f"threads={threads}", "eval_every=50", "tensorboard=false",
           f"hydra.run.dir={run_dir}"]
    print(" ".join(cmd), flush=True)
    rc = subprocess.run(cmd, cwd=REPO, stderr=subprocess.DEVNULL).returncode
    if rc not in (0, 130):
        raise SystemExit(f"gs_train failed with exit status {rc}")
    m = json.loads((run_dir / "metrics.json").read_text())
    res = {"final": {k: m.get(k) for k in ("psnr", "ssim", "n_gaussians", "iters", "seconds", "train_seconds")}}
    for mark in marks:
        rows = [h for h in m["history"] if h["seconds"] <= mark]
        if rows:
            h = rows[-1]
            res[f"{int(mark)}s"] = {"psnr": h["psnr"], "ssim": h["ssim"], "n_gaussians": int(h["n_gaussians"]),
                                    "steps": h["step"], "wall_s": h["seconds"], "train_s": h["train_seconds"]}
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--tile", type=int, default=4)
    ap.add_argument("--short", action="store_true", help="train 3 minutes only (marks 1 and 3 min)")
    ap.add_argument("--no-train", action="store_true", help="rasteriser timing only")
    ap.add_argument("--state", default="", help="a gs_train checkpoint.pt to time instead of the initial model")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    res = {"raster": bench_raster(args)}
    print(json.dumps(res["raster"], indent=1), flush=True)
    out = REPO / "outputs" / "bench_gaussians"
    if not args.no_train:
        marks = [60.0, 180.0] if args.short else [60.0, 180.0, 600.0]
        # one run; its wall clock includes data loading and evaluations (time_budget counts training only)
        res["train"] = bench_train(marks[-1], marks, args.threads, out)
        print(json.dumps(res["train"], indent=1), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
