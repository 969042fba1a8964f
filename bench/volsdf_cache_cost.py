"""The price of one SDF-cache refresh (``SDFGridCache.update``) of a finished volsdf run's field.

    python bench/volsdf_cache_cost.py RUN_DIR SCENE_DIR [--resolution 64] [--repeats 8] [--threads 2]

Loads the run's SDF field (its checkpoint) and times refreshes of a ``resolution``^3 cache over the
scene box (wall and CPU seconds, mean of ``repeats`` after one warm-up). With ``cache_every`` N a run
pays about this / N seconds per training step for its cache.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from volsdf_run import load_sdf_field, run_scene_parser

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing


def main() -> None:
    ap = run_scene_parser(__doc__)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=8)
    args = ap.parse_args()
    import torch
    from l3d_app.render.sdf.cache import SDFGridCache

    torch.set_num_threads(args.threads)
    _, data, model = load_sdf_field(args.run, args.scene)
    lo, hi = data.scene_box.tolist()
    cache = SDFGridCache((lo, hi), args.resolution)
    cache.update(model.sdf)                     # warm-up
    wall, cpu = [], []
    for _ in range(max(1, args.repeats)):
        t0, c0 = time.perf_counter(), time.process_time()
        cache.update(model.sdf)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    n = len(wall)
    print(f"{args.run.name}: {args.resolution}^3 cache refresh {sum(wall) / n:.3f} s wall "
          f"(min {min(wall):.3f}), {sum(cpu) / n:.3f} CPU-s, mean of {n}, {args.threads} threads")


if __name__ == "__main__":
    main()
