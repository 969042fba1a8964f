"""Benchmark: radiance-field configurations on the built-in 64x64 scene, speed against error, at equal
wall time. Run by hand, never in tests:

    python bench/bench_nerf.py [--budget 300] [--target 0] [--threads 1] [--configs train_nerf nerf_baseline]
    python bench/bench_nerf.py --configs nerf_baseline nerf_importance --threads 2     # coarse + fine vs one network

Configurations (``CONFIGS``): ``train_nerf`` (the fast field), ``nerf_baseline`` (the course's NeRF:
``experiment=nerf_baseline``, coarse + fine networks, 64 + 128 samples), ``nerf_importance`` (the same MLP
and sample counts with ONE network as its own no-grad proposal, ``sampler=importance``) and
``nerf_stratified`` (one network, 128 stratified samples).

Each configuration runs through ``main.py`` with ``time_budget = 2 * budget + 60`` WALL seconds
for the whole task (``time_budget`` counts start-up, the frequent validations, the final test
evaluation and ``reserve``; the factor leaves at least ``budget`` seconds of training steps on
a quiet machine, the horizon of the table) and evaluates VALIDATION PSNR (4 val views) every few steps.
Reported: the validation PSNR reached after 30 s, 2 min and 5 min of training (the task's
``train_seconds`` at each evaluation: steps only), the training time each configuration needs
to reach a target PSNR (default: the baseline's validation PSNR at the largest budget), the
speed-up, and the final TEST PSNR (all test views, read once). Writes
``outputs/bench_nerf/results.json`` and a markdown table.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BUDGETS = (30, 60, 120, 300)
CONFIGS = {"train_nerf": ["task=train_nerf"],
           "nerf_baseline": ["experiment=nerf_baseline"],
           "nerf_importance": ["experiment=nerf_baseline", "sampler=importance", "sampler.n_fine=128"],
           "nerf_stratified": ["experiment=nerf_baseline", "sampler=stratified", "sampler.n_samples=128"]}
EVAL_EVERY = {"train_nerf": 10, "nerf_baseline": 25, "nerf_importance": 25, "nerf_stratified": 25}   # steps between val readings


def run_config(task: str, budget: float, threads: int, out: Path, reuse: bool = False) -> list:
    """Run ``task`` within ``budget`` wall seconds; returns [(train_seconds, val psnr, val ssim, step)]
    and the final metrics (test ``psnr`` / ``ssim``)."""
    run_dir = out / task
    if reuse and (run_dir / "metrics.json").exists():
        metrics = json.loads((run_dir / "metrics.json").read_text())
        return [(h["train_seconds"], h["psnr"], h["ssim"], h["step"]) for h in metrics["history"]], metrics
    cmd = [sys.executable, str(REPO / "main.py"), *CONFIGS[task], "iters=1000000", f"time_budget={2 * budget + 60}",
           f"eval_every={EVAL_EVERY.get(task, 50)}", "eval_views=4", "gif_frames=0", f"threads={threads}",
           "tensorboard=false", f"hydra.run.dir={run_dir}"]
    print(" ".join(cmd), flush=True)
    rc = subprocess.run(cmd, cwd=REPO, env={**__import__("os").environ, "L3D_NO_PROGRESS": "1"}).returncode
    if rc not in (0, 130):
        raise SystemExit(f"{task} failed with exit status {rc}")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    hist = [(h["train_seconds"], h["psnr"], h["ssim"], h["step"]) for h in metrics["history"]]
    return hist, metrics


def psnr_at(hist, seconds):
    before = [h for h in hist if h[0] <= seconds * 1.02]
    return before[-1][1] if before else float("nan")


def time_to(hist, target):
    for h in hist:
        if h[1] >= target:
            return h[0]
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--budget", type=float, default=300.0)
    ap.add_argument("--target", type=float, default=0.0, help="PSNR target (0: the baseline's PSNR at the budget)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reuse", action="store_true", help="re-read finished runs instead of training again")
    ap.add_argument("--configs", nargs="+", default=["train_nerf", "nerf_baseline"], choices=sorted(CONFIGS))
    args = ap.parse_args()
    out = REPO / "outputs" / "bench_nerf"
    results = {}
    for task in args.configs:
        hist, metrics = run_config(task, args.budget, args.threads, out, args.reuse)
        results[task] = {"history": hist, "final": {k: v for k, v in metrics.items() if k != "history"}}
    budgets = [b for b in BUDGETS if b <= args.budget * 1.001]
    target = args.target
    if target <= 0 and "nerf_baseline" in results:
        target = psnr_at(results["nerf_baseline"]["history"], budgets[-1])
    lines = ["| config | " + " | ".join(f"val PSNR @ {b:g} s" for b in budgets)
             + f" | time to {target:.2f} dB | steps | samples/ray | occupied | test PSNR |",
             "|---" * (len(budgets) + 6) + "|"]
    for task, r in results.items():
        h, f = r["history"], r["final"]
        lines.append(f"| {task} | " + " | ".join(f"{psnr_at(h, b):.2f}" for b in budgets)
                     + f" | {time_to(h, target):.1f} s | {f['iters']} | "
                     + f"{f['samples_per_ray'] + f.get('coarse_samples_per_ray', 0.0):g} "
                     + f"| {f.get('occupied_fraction', 1.0)} | {f['psnr']:.2f} |")
        r["time_to_target"] = time_to(h, target)
    if {"train_nerf", "nerf_baseline"} <= set(results):
        a, b = results["train_nerf"]["time_to_target"], results["nerf_baseline"]["time_to_target"]
        lines.append(f"\nspeed-up to {target:.2f} dB: {b / a:.1f}x (baseline {b:.1f} s / fast {a:.1f} s)")
    table = "\n".join(lines)
    print(table)
    (out / "results.json").write_text(json.dumps({"target": target, "results": results}, indent=1))
    (out / "table.md").write_text(table + "\n")


if __name__ == "__main__":
    main()
