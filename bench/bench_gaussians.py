"""Benchmark: what each part of Gaussian splatting buys on the course truck, against wall time.

Run by hand, never in tests (each configuration trains for ``--budget`` seconds)::

    python bench/bench_gaussians.py                       # default vs strategy=course, 600 s each
    python bench/bench_gaussians.py --ablations           # + no SH, isotropic, no SSIM, no densification
    python bench/bench_gaussians.py --budget 40 --marks 10,20,40 --doc /tmp/g.md   # a quick check
    python bench/bench_gaussians.py --raster              # also: one fwd+bwd of 10k splats, timed
    python bench/bench_gaussians.py --no-train [--state outputs/.../checkpoint.pt]   # that timing only
    python bench/bench_gaussians.py --short               # 180 s per configuration, marks 1 and 3 min

Each configuration is ONE ``gs_train data=truck`` run through ``main.py`` with
``time_budget=--budget`` (wall seconds of the whole task, evaluations and outputs included),
evaluated on the VALIDATION views every ``--eval-every`` steps. The table gives, per
configuration, the validation PSNR / SSIM of the last evaluation at or before each mark
(1, 3 and 10 minutes by default) and the TEST PSNR / SSIM, read once at the end of the run.
Runs go one after the other (``--threads`` each), so the machine's other load matters:
the table records ``uptime`` before and after. The table is written between the
``<!-- bench:begin -->`` / ``<!-- bench:end -->`` markers of ``--doc`` (default
``docs/gaussians.md``); the rest of that page is kept.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

# name -> (what it is, overrides). The ablations take ONE part away from the default.
NO_DENSIFY = ["strategy=course", "isotropic=false", "ssim_lambda=0.2", "sh_degree=3", "lr.means_final=0.0000016",
              "lr.quats=0.001", "lr.sh_rest=0.000125"]     # course.yaml's fixed set, every other default back
CONFIGS = {
    "default": ("full method: anisotropic, SH 3, L1 + 0.2 SSIM, 3DGS densification", []),
    "course": ("the course's baseline: isotropic, SH 0, L1 only, fixed count", ["strategy=course"]),
}
ABLATIONS = {
    "no_sh": ("default without SH (degree 0)", ["sh_degree=0"]),
    "isotropic": ("default with isotropic splats", ["isotropic=true"]),
    "no_ssim": ("default with L1 only", ["ssim_lambda=0"]),
    "no_densify": ("default without densification (fixed count)", NO_DENSIFY),
}
BEGIN, END = "<!-- bench:begin -->", "<!-- bench:end -->"


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "(uptime unavailable)"


def run_config(name: str, overrides, args) -> dict:
    run_dir = Path(args.out) / name
    cmd = [sys.executable, str(REPO / "main.py"), "task=gs_train", "data=truck", f"data.root={args.root}",
           "iters=10000000", f"time_budget={args.budget}", f"eval_every={args.eval_every}", f"threads={args.threads}",
           f"seed={args.seed}", f"hydra.run.dir={run_dir}", *overrides]
    print("$", " ".join(cmd[1:]), flush=True)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{name} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    m = json.loads((run_dir / "metrics.json").read_text())
    m["wall"] = time.perf_counter() - t0
    return m


def at_mark(history, mark: float):
    """The last evaluation with ``seconds <= mark`` (None if none)."""
    rows = [h for h in history if h["seconds"] <= mark + 1e-6]
    return rows[-1] if rows else None


def table(results, marks, args, load_before: str, load_after: str) -> str:
    head = " | ".join(f"val @ {m / 60:g} min" for m in marks)
    lines = [f"Command: `python bench/bench_gaussians.py {' '.join(sys.argv[1:])}`".rstrip(),
             "", f"Machine load before: `{load_before}`; after: `{load_after}`.", "",
             f"| config | what | {head} | test (end) | Gaussians | steps | s/step |",
             "|" + "---|" * (len(marks) + 6)]
    for name, (what, overrides, m) in results.items():
        cells = []
        for mark in marks:
            h = at_mark(m["history"], mark)
            cells.append("-" if h is None else f"{h['psnr']:.2f} / {h['ssim']:.3f} (step {h['step']})")
        lines.append(f"| `{name}` | {what} | " + " | ".join(cells)
                     + f" | **{m['psnr']:.2f} / {m['ssim']:.3f}** | {m['n_gaussians']} | {m['iters']}"
                     f" | {m['seconds_per_step']:.3f} |")
    lines += ["", "Cells: PSNR (dB) / SSIM. `val @ t`: the validation views (every 20th training frame, "
              "never a test frame), last evaluation at or before t minutes of the task's wall time "
              f"(evaluated every {args.eval_every} steps). `test (end)`: the 5 course test frames, read once "
              f"after the {args.budget:g} s budget. Overrides per config: "
              + "; ".join(f"`{n}`: `{' '.join(o) or '-'}`" for n, (_, o, _) in results.items()) + "."]
    return "\n".join(lines)


def write_doc(path: Path, body: str) -> None:
    text = path.read_text() if path.is_file() else "# Gaussian splatting\n\n"
    block = f"{BEGIN}\n{body}\n{END}"
    if BEGIN in text and END in text:
        text = text[:text.index(BEGIN)] + block + text[text.index(END) + len(END):]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def bench_raster(args) -> dict:
    """One fwd+bwd of the truck's 10k initial splats (SH 3) on one training view: median wall and CPU s."""
    import numpy as np
    import torch

    from l3d_app.data.nerf_formats import truck
    from l3d_app.models.gaussians import init_from_points
    from l3d_app.render.gaussians.rasterize import rasterize_gaussians

    torch.set_num_threads(args.threads)
    root = Path(args.root)
    data = truck(root=str(root))
    pts = torch.from_numpy(np.load(root / "points" / "points_10000.npy").astype(np.float32))
    m = init_from_points(pts, None, opacity=0.1)
    if args.state:                                     # a trained, densified model from a gs_train checkpoint
        m.load_state_dict(torch.load(args.state, weights_only=False)["trainable"]["modules"]["gaussians"])
    cam, target = data.cameras[int(data.train[0])], data.images[int(data.train[0])]
    wall, cpu = [], []
    for i in range(args.repeats + 2):
        t0, c0 = time.perf_counter(), time.process_time()
        out = rasterize_gaussians(m.means, m.log_scales3, m.quats, m.opacity_logits, m.sh, 3, cam, data.background)
        (out["color"][0] - target).abs().mean().backward()
        if i >= 2:
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        for p in m.parameters():
            p.grad = None
    return {"fwd_bwd_median_s": statistics.median(wall), "fwd_bwd_cpu_median_s": statistics.median(cpu),
            "n_tile_overlaps": int(out["n_pairs"].sum()), "n_gaussians": m.num, "threads": args.threads}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--budget", type=float, default=600.0, help="wall seconds per configuration")
    ap.add_argument("--marks", default="60,180,600", help="seconds at which to read the validation figures")
    ap.add_argument("--eval-every", type=int, default=50)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--root", default=str(REPO.parent / "shared" / "data" / "truck"))
    ap.add_argument("--out", default=str(REPO / "outputs" / "bench_gaussians"))
    ap.add_argument("--doc", default=str(REPO / "docs" / "gaussians.md"))
    ap.add_argument("--configs", default="", help="comma list to run a subset (names: "
                    + ", ".join([*CONFIGS, *ABLATIONS]) + ")")
    ap.add_argument("--ablations", action="store_true", help="also run the four one-part-off ablations")
    ap.add_argument("--raster", action="store_true", help="also time one rasteriser fwd+bwd")
    ap.add_argument("--no-train", action="store_true", help="only the rasteriser timing")
    ap.add_argument("--state", default="", help="time this gs_train checkpoint's Gaussians instead")
    ap.add_argument("--short", action="store_true", help="--budget 180 --marks 60,180")
    ap.add_argument("--repeats", type=int, default=10)
    args = ap.parse_args()
    if args.short:
        args.budget, args.marks = 180.0, "60,180"
    marks = [float(x) for x in args.marks.split(",") if x]
    table_of = {**CONFIGS, **(ABLATIONS if args.ablations else {})}
    if args.configs:
        wanted = args.configs.split(",")
        unknown = [n for n in wanted if n not in {**CONFIGS, **ABLATIONS}]
        if unknown:
            raise SystemExit(f"unknown config(s) {unknown}; known: {', '.join([*CONFIGS, *ABLATIONS])}")
        table_of = {n: {**CONFIGS, **ABLATIONS}[n] for n in wanted}
    os.environ.setdefault("L3D_NO_PROGRESS", "1")
    if args.raster or args.no_train:
        print(json.dumps(bench_raster(args), indent=1))
        if args.no_train:
            return
    before = uptime()
    results = {}
    for name, (what, overrides) in table_of.items():
        m = run_config(name, overrides, args)
        results[name] = (what, overrides, m)
        print(f"{name}: test {m['psnr']:.2f} dB / {m['ssim']:.3f}, {m['n_gaussians']} Gaussians, "
              f"{m['iters']} steps, {m['wall']:.0f} s", flush=True)
    body = table(results, marks, args, before, uptime())
    print(body)
    write_doc(Path(args.doc), body)
    print(f"written: {args.doc}")


if __name__ == "__main__":
    main()
