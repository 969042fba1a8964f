"""Benchmark: does SDS with the built-in prior produce what the prompt asks? Run by hand:

    python bench/bench_sds.py [--prompts 12] [--seeds 2] [--scales 0 1 3 10 30] [--spaces pixel latent]
                              [--iters N] [--threads 1] [--extra key=value ...]

Each (space, guidance scale, prompt, seed) runs ``task=sds_image`` through the app (in this
process, one Hydra compose per run, no TensorBoard) and the independent checker scores the
final image. Prompts: fully specified ones ("a red circle on white"), balanced over shapes,
colours and backgrounds (``l3d_app.prompt_vocab.full_prompts``). Reported per
(space, scale): match rate, colour / shape / background accuracy, the match rate per asked
shape, mean seconds per run and the machine's load average.
Writes ``outputs/bench_sds/results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def run_one(overrides, out_dir: Path) -> dict:
    from hydra import compose, initialize_config_dir

    from l3d_app.app import run_task
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        cfg = compose(config_name="config", overrides=list(overrides))
    run_task(cfg, out_dir)
    return json.loads((out_dir / "metrics.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--prompts", type=int, default=12, help="prompts (multiple of 3: balanced over shapes)")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.0, 1.0, 3.0, 10.0, 30.0])
    ap.add_argument("--spaces", nargs="+", default=["pixel", "latent"])
    ap.add_argument("--iters", type=int, default=None, help="default: the task's own")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--extra", nargs="*", default=[], help="more overrides, e.g. lr=0.05")
    ap.add_argument("--out", default=str(REPO / "outputs" / "bench_sds"))
    args = ap.parse_args()
    os.environ.setdefault("L3D_NO_PROGRESS", "1")
    from l3d_app.prompt_vocab import full_prompts
    prompts = full_prompts(max(1, args.prompts // 3))
    out = Path(args.out)
    rows = []
    load0 = os.getloadavg()[0]
    for space in args.spaces:
        for scale in args.scales:
            for pi, prompt in enumerate(prompts):
                for seed in range(args.first_seed, args.first_seed + args.seeds):
                    run_dir = out / space / f"s{scale:g}" / f"p{pi}_seed{seed}"
                    ov = ["task=sds_image", f"prompt='{prompt}'", f"space={space}", f"guidance_scale={scale}",
                          f"seed={seed}", f"threads={args.threads}", "tensorboard=false",
                          *([f"iters={args.iters}"] if args.iters else []),
                          *args.extra]
                    m = run_one(ov, run_dir)
                    rows.append({"space": space, "scale": scale, "prompt": prompt, "seed": seed, **m})
                    print(f"{space:6s} s={scale:<5g} {prompt:28s} seed={seed} match={m['match']} "
                          f"saw=({m['seen_colour']}, {m['seen_shape']}, {m['seen_background']}) "
                          f"{m['seconds']:.1f}s", flush=True)
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    from l3d_app.data.prompt_images import BACKGROUND_NAMES, COLOUR_NAMES, SHAPES, parse_prompt

    def want(r, k):
        return (COLOUR_NAMES, SHAPES, BACKGROUND_NAMES)[k][parse_prompt(r["prompt"])[k]]

    lines = ["| space | guidance scale | match rate | colour | shape | background | circle / square / triangle "
             "| s / run | runs |", "|---|---|---|---|---|---|---|---|---|"]
    for space in args.spaces:
        for scale in args.scales:
            sel = [r for r in rows if r["space"] == space and r["scale"] == scale]
            if not sel:
                continue

            def rate(fn, subset=sel):
                return sum(fn(r) for r in subset) / max(1, len(subset))
            per_shape = " / ".join(f"{rate(lambda r: r['match'], [r for r in sel if want(r, 1) == s]):.0%}"
                                   for s in SHAPES)
            lines.append(f"| {space} | {scale:g} | {rate(lambda r: r['match']):.0%} "
                         f"| {rate(lambda r: r['seen_colour'] == want(r, 0)):.0%} "
                         f"| {rate(lambda r: r['seen_shape'] == want(r, 1)):.0%} "
                         f"| {rate(lambda r: r['seen_background'] == want(r, 2)):.0%} | {per_shape} "
                         f"| {statistics.mean(r['seconds'] for r in sel):.1f} | {len(sel)} |")
    lines.append(f"\nload average (1 min) at the start / end: {load0:.2f} / {os.getloadavg()[0]:.2f}; "
                 f"extra overrides: {' '.join(args.extra) or 'none'}")
    table = "\n".join(lines)
    (out / "results.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
