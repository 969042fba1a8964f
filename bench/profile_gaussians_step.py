"""Where one gs_train step spends its time, stage by stage, on a trained set of Gaussians.

Run by hand, never in tests::

    python bench/profile_gaussians_step.py --root outputs/.cache/bench_scenes/ground \\
        --state RUN_DIR/checkpoint.pt [--views 8 --repeats 5 --threads 2] [--repo OTHER_CHECKOUT]

Loads the Gaussians of a ``gs_train`` checkpoint (``--state``) and a NeRF-synthetic scene
(``--root``), then times, on its first ``--views`` training views, ``--repeats`` times each,
what one training step of ``gs_train`` does: the rasteriser's stages (projection, SH colour,
tile binning, the (pixel, splat) pair test, compositing), the loss (L1 + 0.2 (1 - SSIM)), the
backward pass and one Adam step of all parameters (``fused`` as gs_train builds it, and the
``foreach`` and single-tensor forms for comparison). Wall milliseconds per step, the mean over all timed
steps after two warm-up steps. ``--repo`` times another checkout's code with this script
(e.g. an older commit, for a before/after table): the stage functions are looked up by name
in its ``l3d_app.render.gaussians.rasterize``.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", required=True, help="NeRF-synthetic scene folder")
    ap.add_argument("--state", required=True, help="a gs_train checkpoint.pt")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repo", default=str(REPO), help="checkout whose l3d_app is timed")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(args.repo).resolve()))
    import torch

    import l3d_app.render.gaussians.rasterize as G
    from l3d_app.data.nerf_formats import blender
    from l3d_app.metrics.image import ssim
    from l3d_app.models.gaussians import init_from_points

    torch.set_num_threads(args.threads)
    spent = collections.defaultdict(float)

    def timed(name, fn):
        def wrapper(*a, **k):
            t0 = time.perf_counter()
            out = fn(*a, **k)
            spent[name] += time.perf_counter() - t0
            return out
        return wrapper

    for name in ("project_gaussians", "sh_to_color", "bin_tiles", "splat_pixel_pairs"):
        setattr(G, name, timed(name, getattr(G, name)))
    composite = G.CompositeFunction
    G.CompositeFunction = type("Timed", (), {"apply": staticmethod(timed("composite_forward", composite.apply))})

    data = blender(root=args.root)
    state = torch.load(args.state, map_location="cpu", weights_only=False)["trainable"]["modules"]["gaussians"]
    model = init_from_points(torch.zeros(state["means"].shape[0], 3), None, opacity=0.1)
    model.load_state_dict(state)
    params = list(model.parameters())
    forms = {"fused": {"fused": True}, "foreach": {"foreach": True}, "single_tensor": {"foreach": False}}
    adams = {kind: torch.optim.Adam([{"params": [p], "lr": 0.0} for p in params], **kw) for kind, kw in forms.items()}
    views = [int(i) for i in data.train[:args.views]]

    def step(i: int) -> None:
        t0 = time.perf_counter()
        out = G.rasterize_gaussians(model.means, model.log_scales3, model.quats, model.opacity_logits, model.sh, 3,
                                    data.cameras[i], data.background)
        t1 = time.perf_counter()
        pred, target = out["color"][0], data.images[i]
        loss = (pred - target).abs().mean() + 0.2 * (1 - ssim(pred, target))
        t2 = time.perf_counter()
        loss.backward()
        t3 = time.perf_counter()
        spent["rasterize_total"] += t1 - t0
        spent["loss"] += t2 - t1
        spent["backward"] += t3 - t2
        for kind, opt in adams.items():        # lr 0: the parameters stay as loaded
            t4 = time.perf_counter()
            opt.step()
            spent[f"adam_{kind}"] += time.perf_counter() - t4
        for p in params:
            p.grad = None

    for i in views[:2]:
        step(i)
    spent.clear()
    for _ in range(args.repeats):
        for i in views:
            step(i)
    n = args.repeats * len(views)
    ms = {k: round(1000.0 * v / n, 1) for k, v in spent.items()}
    ms["step_total_fused_adam"] = round(ms["rasterize_total"] + ms["loss"] + ms["backward"] + ms["adam_fused"], 1)
    print(json.dumps({"repo": args.repo, "gaussians": model.num, "steps_timed": n, "threads": args.threads,
                      "ms_per_step": ms}, indent=1))


if __name__ == "__main__":
    main()
