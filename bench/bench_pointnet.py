"""Benchmark: default pointnet_cls and pointnet_seg training on the built-in dataset.

    python bench/bench_pointnet.py [extra overrides...]     # e.g. threads=2

Runs ``python main.py task=pointnet_cls`` and ``task=pointnet_seg`` with their defaults
(plus any overrides) into outputs/bench_pointnet/<task>, then prints accuracy, wall
seconds (including first-use data generation when the cache is cold) and model size.
Targets (issue 9): 2 CPU cores, within 5 minutes each: classification test accuracy
>= 0.97, segmentation point accuracy >= 0.90. Run by hand; never part of the tests.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(extra):
    rows = []
    for task in ("pointnet_cls", "pointnet_seg"):
        out = REPO / "outputs" / "bench_pointnet" / task
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "main.py", f"task={task}", f"hydra.run.dir={out}", *extra],
                       cwd=REPO, check=True)
        wall = time.perf_counter() - t0
        m = json.loads((out / "metrics.json").read_text())
        rows.append((task, m["accuracy"], m.get("miou", float("nan")), m["seconds"], wall,
                     m["train_seconds"], m["n_params"]))
    print("| task | test accuracy | mIoU | task seconds | process wall s | train s | params |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r[0]} | {r[1]:.4f} | {r[2]:.4f} | {r[3]:.1f} | {r[4]:.1f} | {r[5]:.1f} | {r[6]} |")


if __name__ == "__main__":
    main(sys.argv[1:])
