"""Benchmark: the grid table's gradient accumulation on CPU -- autograd's ``index_add_`` (the
backward of ``index_select``) against :func:`l3d_app.models.table_gather.scatter_rows` (one weighted
``torch.bincount`` per feature column). Run by hand, never in tests:

    python bench/bench_table_gather.py [--threads 2] [--rows 700000] [--points 17408] [--levels 8]
        [--features 2] [--repeats 10]

The index has ``8 x points x levels`` entries drawn uniformly from ``rows`` (volsdf's default SDF
grid: 8 levels of 2 features, ~700k table rows; a step gathers at ~17k points: 16 fine samples of
1024 rays plus 1024 eikonal points). Prints the median and minimum seconds of each and the largest
difference between their results (float32 sums in a different order).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing


def main() -> None:
    from l3d_app.models.table_gather import scatter_rows

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rows", type=int, default=700000)
    ap.add_argument("--points", type=int, default=17408)
    ap.add_argument("--levels", type=int, default=8)
    ap.add_argument("--features", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=10)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    m = 8 * args.points * args.levels
    index = torch.randint(0, args.rows, (m,), generator=gen)
    values = torch.randn(m, args.features, generator=gen)
    ways = {"index_add_": lambda: torch.zeros(args.rows, args.features).index_add_(0, index, values),
            "bincount (scatter_rows)": lambda: scatter_rows(values, index, args.rows)}
    seconds = {name: [] for name in ways}
    results = {name: fn() for name, fn in ways.items()}          # warm-up
    for _ in range(args.repeats):                                # round-robin
        for name, fn in ways.items():
            t0 = time.perf_counter()
            fn()
            seconds[name].append(time.perf_counter() - t0)
    print(f"{m} rows of {args.features} features into {args.rows} table rows, threads={args.threads}, "
          f"torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}")
    for name, ts in seconds.items():
        print(f"  {name:24s} median {1e3 * statistics.median(ts):7.1f} ms, min {1e3 * min(ts):7.1f} ms")
    a, b = results.values()
    print(f"  largest difference {float((a - b).abs().max()):.2e}")


if __name__ == "__main__":
    main()
