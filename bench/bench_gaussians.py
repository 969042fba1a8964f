"""Benchmark: Gaussian rasteriser forward+backward on one truck view, and gs_train under
time budgets. Run by hand, never in tests:

    python bench/bench_gaussians.py [--threads 2] [--repeats 20] [--tile 4]
                                    [--train-budgets 60 180 600]   # (omit to skip training)

Part 1: 10k Gaussians initialised from points_10000.npy (isotropic scales = mean distance
to the 3 nearest neighbours, opacity 0.1, grey DC colour, SH degree 3 coefficients),
one 160x90 training view; median of ``--repeats`` fwd+bwd, peak RSS growth (resource) and
tracemalloc peak (Python-side only). Part 2: ``gs_train data=truck time_budget=B`` through
main.py for each budget; prints test PSNR / SSIM / Gaussian count.
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
    params = [p.detach().clone().requires_grad_(True) for p in
              (model.means, model.log_scales, model.quats, model.opacity_logits, model.sh)]
    cam = data.cameras[int(data.train[0])]
    target = data.images[int(data.train[0])]
    times = []
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    n_pairs = 0
    for i in range(args.repeats + 2):
        t0 = time.perf_counter()
        out = rasterize_gaussians(*params, 3, cam, data.background, tile_size=args.tile)
        loss = (out["color"][0] - target).abs().mean()
        loss.backward()
        dt = time.perf_counter() - t0
        for p in params:
            p.grad = None
        n_pairs = int(out["n_pairs"].sum())
        if i >= 2:
            times.append(dt)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    res = {"fwd_bwd_median_s": statistics.median(times), "fwd_bwd_min_s": min(times),
           "peak_rss_mb": rss / 1024, "rss_growth_mb": (rss - rss0) / 1024, "n_pairs": n_pairs,
           "threads": torch.get_num_threads(), "tile": args.tile}
    return res


def bench_train(budget: float, threads: int, out: Path) -> dict:
    run_dir = out / f"truck_{int(budget)}s"
    cmd = [sys.executable, str(REPO / "main.py"), "task=gs_train", "data=truck", "iters=1000000",
           f"time_budget={budget}", f"threads={threads}", "gif_frames=0", "tensorboard=false",
           f"hydra.run.dir={run_dir}"]
    print(" ".join(cmd), flush=True)
    rc = subprocess.run(cmd, cwd=REPO).returncode
    if rc not in (0, 130):
        raise SystemExit(f"gs_train failed with exit status {rc}")
    m = json.loads((run_dir / "metrics.json").read_text())
    return {k: m.get(k) for k in ("psnr", "ssim", "n_gaussians", "iters", "seconds", "train_seconds")}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--tile", type=int, default=4)
    ap.add_argument("--train-budgets", type=float, nargs="*", default=[])
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    res = {"raster": bench_raster(args)}
    print(json.dumps(res["raster"], indent=1), flush=True)
    out = REPO / "outputs" / "bench_gaussians"
    for b in args.train_budgets:
        res[f"train_{int(b)}s"] = bench_train(b, args.threads, out)
        print(json.dumps(res[f"train_{int(b)}s"]), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
