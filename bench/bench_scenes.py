"""Benchmark on scenes we did not make: the defaults of train_nerf, gs_train, volsdf and surfels (and
the course NeRF within the same 600 s wall limit as the in-run baseline) on every Mitsuba scene of
``bench/make_scenes.py``. Run by hand, never in tests:

    python bench/make_scenes.py                         # once: renders the scenes (cached)
    python bench/bench_scenes.py [--scenes dev thin ...] [--methods train_nerf gs_train volsdf surfels nerf_baseline]
                                 [--threads 2] [--baseline-budget 590] [--reuse] [--doc docs/benchmark_scenes.md]

Each run is ``python main.py task=<method> data=blender data.root=<scene>`` with the task's
defaults (``train_nerf`` adds ``extract_mesh=true`` so its surface can be scored;
``nerf_baseline`` gets ``time_budget=--baseline-budget``: the 590 s the other defaults take, so
its row says what the course settings reach in the same wall time, evaluation of all 20 test
views at 128 samples per ray included). Reported per run: test PSNR / SSIM
on ALL test views (the task's own ``psnr``/``ssim``, read once at its end), wall seconds of
the whole task, model size (parameters or Gaussians), and for runs that leave a mesh
(``*.ply`` other than Gaussian point clouds, or ``mesh.obj``): chamfer on the whole true
surface and on the part the training cameras observe (% of the true bounding-box diagonal),
F1 at 0.02 and 0.05 (observed), and the phantom area: the share of the mesh's area farther
than 0.05 from the true surface (= 1 - precision at 0.05, from area-uniform samples).

The development scenes (``dev``, ``ground``) are the only scenes any default may be tuned on; the
others are held out (``scene.json`` says which), except where a method's choice looked at one
(``DIAGNOSIS``: volsdf on ``thin`` and, for its evaluation cost only, on ``around``), which its
rows say. ``--render-only`` writes the table and plot again from the ledger, running nothing. Writes ``outputs/bench_scenes/results.json``, the
markdown table and a plot of PSNR against seconds (``--doc``, default
``docs/benchmark_scenes.md`` + ``.png``).

The table is a ledger: every row carries the commit it was measured at (``+dirty`` when the
working tree had uncommitted changes), the machine (cores, CPU model, torch's CPU capability) and
its load average at the end of the run, and is kept in ``docs/benchmark_scenes.json`` (next to
``--doc``). ``bench/ledger_tables.py`` writes one method's rows into its measured page. A call that runs
some scenes or methods replaces those rows and keeps the others as they were measured, so a
re-run of one method does not need the hours of the others (``--fresh`` drops the old rows).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DEFAULT_SCENES = Path(os.environ.get("L3D_BENCH_SCENES", REPO / "outputs" / ".cache" / "bench_scenes"))
METHODS = ("train_nerf", "gs_train", "volsdf", "surfels", "nerf_baseline")
EXTRA = {"train_nerf": ["extract_mesh=true"],
         # the in-run baseline: test PSNR at a fixed budget, no turntable. Its evaluation is slow (128
         # samples per ray, no empty-space skipping: 15-18 s per 128 px view on 2 cores), so the loop
         # must learn that cost early to keep the test views inside the budget: one validation view
         # every 25 steps and no 'before' picture (set before any baseline row was read)
         "nerf_baseline": ["gif_frames=0", "before_after=false", "eval_every=25", "eval_views=1"]}
# A held-out scene that a method's choices looked at: its row for that method is not a held-out
# reading (docs/benchmark_scenes.md, "Choices made on these scenes").
DIAGNOSIS = {("thin", "volsdf"): "diagnosis (volsdf's mask loss weight was chosen after reading it)",
             ("around", "volsdf"): "held out; diagnosis of evaluation cost (wall time only)"}
TARGETS = {"train_nerf": "psnr >= 32", "gs_train": "psnr >= 33",
           "volsdf": "chamfer <= 1% diag, F1@0.02 obs >= 0.8, psnr >= 28, phantom < 5%",
           "surfels": "observed chamfer <= 0.5% diag, F1@0.02 obs >= 0.85, phantom < 5%, psnr >= 30, fewer seconds "
                      "than volsdf's row"}


def run_method(method: str, scene: Path, out: Path, threads: int, baseline_budget: float,
               reuse: bool, overrides: List[str] = ()) -> Optional[dict]:
    """Run one task on one scene through main.py; returns its metrics.json (or None on failure)."""
    run_dir = out / scene.name / method
    stamp_file = run_dir / "measured_at.json"
    if reuse and (run_dir / "metrics.json").is_file():
        metrics = json.loads((run_dir / "metrics.json").read_text())
        metrics["measured_at"] = json.loads(stamp_file.read_text()) if stamp_file.is_file() else {"commit": "unknown"}
        return metrics
    stamp = measured_at()                      # the code this run measures: taken before it starts
    cmd = [sys.executable, str(REPO / "main.py"), f"task={method}", "data=blender", f"data.root={scene}",
           "data.mesh_path=mesh.ply",
           f"threads={threads}", f"hydra.run.dir={run_dir}", *EXTRA.get(method, []), *overrides]
    if method == "nerf_baseline":
        cmd.append(f"time_budget={baseline_budget}")
    print(" ".join(cmd), flush=True)
    t0 = time.perf_counter()
    rc = subprocess.run(cmd, cwd=REPO, env={**os.environ, "L3D_NO_PROGRESS": "1"}).returncode
    if rc != 0 or not (run_dir / "metrics.json").is_file():
        print(f"  {method} on {scene.name} failed (exit {rc})", flush=True)
        return None
    metrics = json.loads((run_dir / "metrics.json").read_text())
    metrics.setdefault("wall_seconds", round(time.perf_counter() - t0, 1))
    stamp["load"] = round(os.getloadavg()[0], 1)   # at the run's end
    stamp_file.write_text(json.dumps(stamp))
    metrics["measured_at"] = stamp
    return metrics


def measured_at() -> Dict[str, object]:
    """What a row measured and where: short commit (``+dirty`` with uncommitted changes), the
    machine, 1-minute load average."""
    def git(*a):
        return subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True).stdout.strip()
    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    if git("status", "--porcelain", "--untracked-files=no", "--", "l3d_app", "conf", "main.py"):
        commit += "+dirty"
    return {"commit": commit, "machine": machine(), "load": round(os.getloadavg()[0], 1)}


def machine() -> str:
    """The machine a row ran on: cores, CPU model and torch's CPU capability, e.g.
    ``2 cores, AMD EPYC 7B13, AVX512``."""
    model = ""
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), "")
    except OSError:
        pass
    try:
        import torch

        capability = torch.backends.cpu.get_cpu_capability()
    except Exception:            # no torch build that reports it
        capability = ""
    return ", ".join(p for p in (f"{os.cpu_count()} cores", model, capability) if p)


def merge_rows(old: List[dict], new: List[dict]) -> List[dict]:
    """The ledger after a call: ``new`` rows replace ``old`` ones of the same (scene, method),
    the rest of ``old`` is kept; sorted by scene (old order first) and METHODS order."""
    key = lambda r: (r["scene"], r["method"])
    fresh = {key(r): r for r in new}
    rows = [fresh.pop(key(r), r) for r in old] + list(fresh.values())
    scenes = list(dict.fromkeys(r["scene"] for r in old + new))
    order = {m: i for i, m in enumerate(METHODS)}
    return sorted(rows, key=lambda r: (scenes.index(r["scene"]), order.get(r["method"], len(order))))


def find_mesh(run_dir: Path) -> Optional[Path]:
    """The surface a run extracted (not a Gaussian point cloud)."""
    for pattern in ("mesh*.ply", "*.ply", "mesh*.obj", "*.obj"):
        for p in sorted(run_dir.glob(pattern)):
            if p.name != "point_cloud.ply":
                return p
    return None


def mesh_scores(mesh_path: Path, scene: Path) -> Dict[str, float]:
    """Whole / observed chamfer (% of diagonal), F1@0.02 and 0.05, phantom share of area."""
    from l3d_app.geometry.mesh_io import load_mesh

    return scores_of_mesh(load_mesh(str(mesh_path)), scene)


def scores_of_mesh(pred, scene: Path) -> Dict[str, float]:
    """:func:`mesh_scores` of a loaded ``Mesh`` against ``scene``'s true mesh and training cameras."""
    from l3d_app.data.nerf_formats import blender
    from l3d_app.geometry.mesh_io import load_mesh
    from l3d_app.metrics.surface_scores import surface_scores
    from l3d_app.render.mesh.rgbd import true_depth_maps

    truth = load_mesh(str(scene / "mesh.ply"))
    data = blender(root=str(scene), background="white")
    cams = data.cameras[data.train]
    depth = true_depth_maps(truth, cams, scale=4)
    s05 = surface_scores(pred, truth, cameras=cams, depth_maps=depth, threshold=0.05)
    s02 = surface_scores(pred, truth, cameras=cams, depth_maps=depth, threshold=0.02)
    return {"chamfer_pct": 100 * s05["chamfer_rel_diag"], "chamfer_obs_pct": 100 * s05["chamfer_observed_rel_diag"],
            "f1_02_obs": s02["f1_observed"], "f1_05_obs": s05["f1_observed"], "f1_05": s05["f1"],
            "phantom_pct": 100 * (1.0 - s05["precision"]), "observed_fraction": s05["observed_fraction"]}


BEGIN, END = "<!-- bench_scenes:begin -->", "<!-- bench_scenes:end -->"


def write_section(doc: Path, section: str) -> None:
    """Replace the text between the BEGIN/END markers of ``doc`` (or start the file with it)."""
    text = doc.read_text() if doc.is_file() else "# Benchmark on scenes we did not make (Mitsuba 3)\n\n"
    if BEGIN in text and END in text:
        text = text[:text.index(BEGIN)] + section + text[text.index(END) + len(END):]
    else:
        text = text + section + "\n"
    doc.parent.mkdir(parents=True, exist_ok=True)
    doc.write_text(text)


def fmt(v, spec: str) -> str:
    return "" if v is None else format(v, spec)


def load_text(row: dict) -> str:
    """The row's load average; rows copied from an older table by hand carry the figure that
    table's prose gave ("about 2"), marked as such."""
    load = fmt(row.get("load"), ".1f") or "?"
    return f"about {load} (from the older table)" if row.get("transcribed_from_table") else load


def role_of(row: dict) -> str:
    """The row's role: its scene's (``scene.json``), unless the method's choices looked at that scene."""
    role = DIAGNOSIS.get((row["scene"], row["method"]))
    return role if role and row["role"] == "held out" else row["role"]


DENSITY_NAMES = {"neus": "NeuS", "volsdf": "VolSDF"}
"""How the table names the density a volsdf row ran with (``density=auto`` picks it from the cameras)."""


def table(rows: List[dict]) -> str:
    head = ("| scene | role | method | test PSNR | test SSIM | seconds | size | chamfer % diag (whole / observed) "
            "| F1@0.02 obs | F1@0.05 obs | phantom % | measured (commit, machine, load) |\n"
            "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    lines = [head]
    for r in rows:
        size = r.get("n_gaussians") or r.get("n_params")
        cham = "" if r.get("chamfer_pct") is None else f"{r['chamfer_pct']:.2f} / {r['chamfer_obs_pct']:.2f}"
        method = r["method"] + (f" ({DENSITY_NAMES.get(r['density'], r['density'])})" if r.get("density") else "")
        method += f" ({' '.join(r['overrides'])}: not the defaults)" if r.get("overrides") else ""
        lines.append(f"| {r['scene']} | {role_of(r)} | {method} | {fmt(r.get('psnr'), '.2f')} | "
                     f"{fmt(r.get('ssim'), '.3f')} | {fmt(r.get('seconds'), '.0f')} | {size or ''} | {cham} | "
                     f"{fmt(r.get('f1_02_obs'), '.3f')} | {fmt(r.get('f1_05_obs'), '.3f')} | {fmt(r.get('phantom_pct'), '.1f')} | "
                     f"{r.get('commit', '?')}, {r.get('machine', 'machine not recorded')}, {load_text(r)} |")
    return "\n".join(lines)


def plot(rows: List[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for method in METHODS:
        pts = [(r["seconds"], r["psnr"]) for r in rows if r["method"] == method and r.get("psnr") is not None]
        if pts:
            ax.scatter(*zip(*pts), label=method)
    ax.set_xlabel("wall seconds (whole task)")
    ax.set_ylabel("test PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=DEFAULT_SCENES, help="folder of make_scenes.py output")
    ap.add_argument("--scenes", nargs="*", default=None)
    ap.add_argument("--methods", nargs="*", default=list(METHODS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--baseline-budget", type=float, default=590.0,
                    help="nerf_baseline's time_budget (s): the wall limit the defaults meet")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "bench_scenes")
    ap.add_argument("--doc", type=Path, default=REPO / "docs" / "benchmark_scenes.md")
    ap.add_argument("--reuse", action="store_true", help="reuse finished runs in --out")
    ap.add_argument("--fresh", action="store_true", help="start the ledger anew instead of merging "
                    "into the rows of docs/benchmark_scenes.json")
    ap.add_argument("--override", nargs="*", default=[], help="extra overrides for every run (smoke tests only: "
                    "the benchmark's figures are the defaults)")
    ap.add_argument("--render-only", action="store_true", help="run nothing: write --doc's table and plot again "
                    "from its ledger (the .json beside it), keeping its 'Last call' line")
    args = ap.parse_args()
    if args.render_only:
        render_from_ledger(args.doc)
        return
    scenes = [args.root / s for s in args.scenes] if args.scenes else sorted(
        p for p in args.root.iterdir() if (p / "scene.json").is_file())
    if not scenes:
        raise SystemExit(f"no scenes under {args.root}: run python bench/make_scenes.py first")
    rows = []
    for scene in scenes:
        info = json.loads((scene / "scene.json").read_text())
        for method in args.methods:
            m = run_method(method, scene, args.out, args.threads, args.baseline_budget, args.reuse, args.override)
            row = {"scene": scene.name, "role": info["role"], "method": method}
            if args.override:      # not the defaults: the row says so (the table prints them beside the method)
                row["overrides"] = list(args.override)
            if m is not None:
                row.update(m["measured_at"])
                row.update({k: m.get(k) for k in ("psnr", "ssim", "seconds", "n_params", "n_gaussians", "iters")})
                if m.get("density"):       # volsdf: the density its cameras chose (density=auto)
                    row["density"] = m["density"]
                mesh = find_mesh(args.out / scene.name / method)
                if mesh is not None:
                    row.update(mesh_scores(mesh, scene))
            rows.append(row)
            print(table([row]).splitlines()[-1], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    ledger = args.doc.with_suffix(".json")
    if not args.fresh and ledger.is_file():
        rows = merge_rows(json.loads(ledger.read_text()), rows)
    ledger.parent.mkdir(parents=True, exist_ok=True)
    ledger.write_text(json.dumps(rows, indent=1) + "\n")
    cmd = "python bench/bench_scenes.py " + " ".join(sys.argv[1:])
    last_call = f"Last call: `{cmd.strip()}` ({os.cpu_count()} cores)."
    write_section(args.doc, section_text(last_call, ledger.name, rows))
    plot(rows, args.doc.with_suffix(".png"))
    print(table(rows))


def section_text(last_call: str, ledger_name: str, rows: List[dict]) -> str:
    """The doc's table section: the last call, how rows are kept, the targets, the table."""
    return (f"{BEGIN}\n{last_call} Each row says the commit, machine and "
            f"load average of its own run; rows not re-run by a call are kept from `{ledger_name}`. "
            "Targets on held-out scenes: "
            + "; ".join(f"{k}: {v}" for k, v in TARGETS.items()) + ".\n\n" + table(rows) + f"\n{END}")


def render_from_ledger(doc: Path) -> None:
    """``--render-only``: the table and plot of ``doc`` from its ledger, nothing run; the section's
    'Last call' sentence is kept (it names the call that measured the newest rows)."""
    ledger = doc.with_suffix(".json")
    if not ledger.is_file():
        raise SystemExit(f"no ledger {ledger}: nothing to render")
    rows = json.loads(ledger.read_text())
    text = doc.read_text() if doc.is_file() else ""
    start = text.find("Last call: `")
    last_call = text[start:text.index(" cores).", start) + len(" cores).")] if start >= 0 else "Last call: unknown."
    write_section(doc, section_text(last_call, ledger.name, rows))
    plot(rows, doc.with_suffix(".png"))
    print(table(rows))


if __name__ == "__main__":
    main()
