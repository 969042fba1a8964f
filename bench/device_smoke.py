"""Device smoke test: run every task once, briefly, on one device, and tabulate what happened.

    python bench/device_smoke.py                          # device=cuda, every conf/task/*.yaml
    python bench/device_smoke.py --device cpu --only render360 sphere_trace
    python bench/device_smoke.py --jobs 4 --timeout 150   # 4 tasks at a time (GPU machine)
    python bench/device_smoke.py --shared-data DIR        # where box/ lives (default ../shared/data)

For each task it runs ``python main.py task=T device=D <short settings>`` in a subprocess with
a per-task timeout, into its own folder of a temporary directory (``--keep`` prints which and
keeps it), and prints one line per task: task, return code, wall seconds, the device the run
recorded in its ``metrics.json`` (a silent CPU fallback shows as ``cpu``) and, when it failed,
the last error line of its output. The short settings (:data:`SHORT`) cut every iteration,
step, epoch, frame and data-size knob so that the sweep of all tasks stays within a few
minutes on a GPU; a task without an entry runs with its defaults. Tasks that read a trained
run (``render_path``, ``gs_render``, ``svr_eval``) run after the task that makes it
(:data:`AFTER`); ``render_path`` is also tried on a volsdf checkpoint and a 3DGS PLY. ``box``
needs the course's images (``<shared-data>/box``) and is skipped when they are absent. Run by
hand; never part of the tests.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: Short settings per task (run name -> overrides). ``{out}``: the run's folder; ``{shared}``:
#: the shared data folder. A run name ``task:variant`` runs ``task`` (the part before ':').
_NERF_DATA = ["data.n_train=20", "data.n_val=2", "data.n_test=2", "data.cache_dir={out}/cache"]
_FRAMES = ["num_frames=2", "batch_frames=2"]
_POINTNET = ["epochs=2", "batch_size=16", "train_points=256", "eval_points=256", "num_vis=1",
             "vis_failures=false", "vis_points=256", "num_frames=2", "image_size=32",
             "data.train_per_class=10", "data.test_per_class=4", "data.num_points=1000",
             "data.cache_dir={out}/cache"]
_SVR = ["eval_objects=2", "num_vis=1", "num_frames=2", "turntable_size=32", "vis_points=256",
        "eval_points=256"]
SHORT = {
    "box": ["iters=20", "eval_every=10", "gif_frames=2", "turntable_size=32", "data.root={shared}/box"],
    "dolly": ["image_size=64", *_FRAMES],
    "fit_mesh": ["iters=20", "eval_every=10", "image_size=32", *_FRAMES, "ico_level=2",
                 "num_samples=1000", "eval_samples=1000"],
    "fit_point": ["iters=20", "eval_every=10", "image_size=32", *_FRAMES, "num_points=1000"],
    "fit_vox": ["iters=20", "eval_every=10", "image_size=32", *_FRAMES, "voxel_size=16"],
    "gs_render": ["num_frames=2", "image_size=64"],
    "gs_train": ["iters=40", "eval_every=20", "n_init=1000", "sh_every=10", "lr_decay_steps=40",
                 "time_budget=90", "reserve=5", *_NERF_DATA],
    "nerf_baseline": ["iters=20", "eval_every=10", "sampler.n_samples=32", "batch_rays=256", "gif_frames=2",
                      "turntable_size=32", "time_budget=90", "reserve=5", *_NERF_DATA],
    "neural_sdf": ["iters=40", "eval_every=20", "batch_points=512", "gif_frames=2", "turntable_size=32",
                   "mesh_resolution=32", "eval_points=2000"],
    "pca_normals": ["image_size=64"],
    "pointnet_cls": _POINTNET,
    "pointnet_seg": _POINTNET,
    "pointnet_robustness": [*_POINTNET, "rotation_degrees=[0,90]", "num_points_list=[500,100]"],
    "ray_diagnostics": ["image_size=64"],
    "render360": ["image_size=64", *_FRAMES],
    "render_path": ["num_frames=3", "image_size=32"],
    "render_path:volsdf": ["num_frames=3", "image_size=32"],
    "render_path:gs": ["num_frames=3", "image_size=32"],
    "sampling_variance": ["rays=500"],
    "sds_image": ["iters=20", "frame_every=10"],
    "sds_mesh": ["iters=10", "eval_every=5", "eval_views=2", *_FRAMES, "turntable_size=32", "png_frames=2"],
    "sds_nerf": ["iters=10", "eval_every=5", "eval_views=2", "num_frames=2", "turntable_size=32"],
    "sphere_trace": ["image_size=64", "num_frames=2"],
    "stereo_depth": ["image_size=64", "trials=2"],
    "surface_tradeoff": ["num_samples_list=[1000]", "resolutions=[16]", "reference_samples=5000",
                         "mesh_samples=2000"],
    "svr_eval": _SVR,
    "svr_train": ["iters=20", "batch_size=8", "eval_every=10", "quick_eval_objects=2", "checkpoint_every=10",
                  *_SVR, "data.train_per_class=10", "data.test_per_class=2", "data.cache_dir={out}/cache"],
    "train_nerf": ["iters=40", "eval_every=20", "batch_rays=512", "sampler.n_samples=32", "gif_frames=2",
                   "turntable_size=32", "extract_mesh=true", "mesh_resolution=32", "time_budget=90",
                   "reserve=5", *_NERF_DATA],
    "train_prior": ["iters=20", "ae_iters=10", "warmup_steps=2", "eval_every=10", "eval_prompts=3",
                    "sample_steps=2", "latent_scale_batch=16", "batch_size=8", "checkpoint_every=10"],
    "volsdf": ["iters=30", "stages.sphere_init.steps=10", "warmup_steps=5", "stages.coarse_to_fine.every=10",
               "eval_every=15", "gif_frames=2", "turntable_size=32", "mesh_resolution=32",
               "eval_points=2000", "supersample=1", "time_budget=90", "reserve=5", *_NERF_DATA],
}
#: Runs that read another run's output: run name -> (producer, overrides with ``{dep}`` = its folder).
AFTER = {
    "render_path": ("train_nerf", ["checkpoint={dep}"]),
    "render_path:volsdf": ("volsdf", ["checkpoint={dep}"]),
    "render_path:gs": ("gs_train", ["ply={dep}/point_cloud.ply"]),
    "gs_render": ("gs_train", ["ply={dep}/point_cloud.ply"]),
    "svr_eval": ("svr_train", ["checkpoint={dep}"]),
}


def all_runs() -> list:
    """Every task of conf/task/*.yaml, plus the extra variants of :data:`SHORT`, sorted."""
    tasks = {p.stem for p in (REPO / "conf" / "task").glob("*.yaml")}
    return sorted(tasks | {n for n in SHORT if n.split(":")[0] in tasks})


def last_error_line(text: str) -> str:
    """The last line that looks like an error (else the last non-empty line), shortened."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if "Error" in ln or "error:" in ln or "Exception" in ln:
            return ln[:300]
    return lines[-1][:300] if lines else ""


def run_one(name: str, device: str, root: Path, shared: Path, timeout: float, threads: int,
            dep_result: dict = None) -> dict:
    """Run one task; return {name, rc, wall, device, error}."""
    task, out = name.split(":")[0], root / name.replace(":", "__")
    row = {"name": name, "rc": None, "wall": 0.0, "device": "-", "error": ""}
    if dep_result is not None and dep_result["rc"] != 0:
        row["error"] = f"skipped: {dep_result['name']} failed"
        return row
    if task == "box" and not (shared / "box").is_dir():
        row["error"] = f"skipped: needs {shared / 'box'} (../shared/data does not travel)"
        return row
    fmt = {"out": out, "shared": shared, "dep": root / AFTER[name][0] if name in AFTER else ""}
    extra = [o.format(**fmt) for o in SHORT.get(name, []) + (AFTER[name][1] if name in AFTER else [])]
    cmd = [sys.executable, "main.py", f"task={task}", f"device={device}", f"hydra.run.dir={out}", *extra]
    if threads > 0:
        cmd.append(f"threads={threads}")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout,
                              env={**os.environ, "L3D_DEBUG": "1"})     # tracebacks, not one-liners
        row["rc"], text = proc.returncode, proc.stdout + "\n" + proc.stderr
    except subprocess.TimeoutExpired as err:
        row["rc"] = "timeout"
        text = (err.stdout or b"").decode(errors="replace") + "\n" + (err.stderr or b"").decode(errors="replace")
        text += f"\ntimed out after {timeout:.0f} s"
    row["wall"] = time.perf_counter() - t0
    (out / "smoke_output.log").write_text(" ".join(cmd) + "\n" + text)
    metrics = out / "metrics.json"
    if metrics.is_file():
        try:
            row["device"] = str(json.loads(metrics.read_text()).get("device", "?"))
        except ValueError:
            row["device"] = "?"
    if row["rc"] != 0:
        row["error"] = last_error_line(text)
        row["tail"] = text.strip().splitlines()
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda", help="device= passed to every task (cuda | cpu | auto)")
    ap.add_argument("--only", nargs="+", default=None, help="run names to run (default: all)")
    ap.add_argument("--timeout", type=float, default=150.0, help="seconds per task")
    ap.add_argument("--jobs", type=int, default=1, help="tasks run at the same time")
    ap.add_argument("--threads", type=int, default=None,
                    help="threads= of every task (default: cores // jobs when jobs > 1, else the task's own)")
    ap.add_argument("--shared-data", default=str(REPO.parent / "shared" / "data"),
                    help="folder holding box/ (the course's box images)")
    ap.add_argument("--keep", action="store_true", help="keep the runs' folders (path printed)")
    ap.add_argument("--tail", type=int, default=40, help="lines of each failed run's output printed at the end")
    args = ap.parse_args(argv)

    names = args.only or all_runs()
    unknown = [n for n in names if n not in all_runs()]
    if unknown:
        ap.error(f"unknown task(s) {unknown}; known: {' '.join(all_runs())}")
    # a run that reads another's output needs its producer in the sweep (once, however many read it)
    names += sorted({AFTER[n][0] for n in names if n in AFTER} - set(names))
    threads = args.threads if args.threads is not None else (
        max(1, (os.cpu_count() or 1) // args.jobs) if args.jobs > 1 else 0)
    shared = Path(args.shared_data).resolve()
    root = Path(tempfile.mkdtemp(prefix="device_smoke_"))
    if args.device.startswith("cuda"):
        import torch

        gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none visible"
        print(f"torch {torch.__version__}, CUDA device: {gpu}", flush=True)
    print(f"device={args.device}, {len(names)} runs, {args.jobs} at a time, timeout {args.timeout:.0f} s, "
          f"folder {root}", flush=True)

    # producers first, so that a dependent run never waits on a task still queued behind it
    first = [n for n in names if n not in AFTER]
    then = [n for n in names if n in AFTER]
    rows, futures = {}, {}
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        def launch(name):
            dep_fut = futures[AFTER[name][0]] if name in AFTER else None   # launched first (above)

            def job():
                dep_row = dep_fut.result() if dep_fut is not None else None
                row = run_one(name, args.device, root, shared, args.timeout, threads, dep_row)
                print(_line(row), flush=True)
                return row
            futures[name] = pool.submit(job)

        for n in first + then:
            launch(n)
        for n in names:
            rows[n] = futures[n].result()
    total = time.perf_counter() - t0

    for n in sorted(rows):
        if rows[n].get("tail") and args.tail > 0:
            print(f"\n--- {n}: last {args.tail} lines of its output ---")
            print("\n".join(rows[n]["tail"][-args.tail:]))
    print(f"\n{'run':<22} {'rc':>7} {'wall s':>7}  {'device':<7} error")
    for n in sorted(rows):
        print(_line(rows[n]))
    failed = [n for n, r in rows.items() if r["rc"] not in (0, None)]
    skipped = [n for n, r in rows.items() if r["rc"] is None]
    print(f"\n{len(rows) - len(failed) - len(skipped)} ok, {len(failed)} failed {failed}, "
          f"{len(skipped)} skipped {skipped}; {total:.1f} s in all")
    if args.keep:
        print(f"runs kept in {root}")
    else:
        shutil.rmtree(root, ignore_errors=True)
    return 1 if failed else 0


def _line(row: dict) -> str:
    rc = "-" if row["rc"] is None else str(row["rc"])
    return f"{row['name']:<22} {rc:>7} {row['wall']:>7.1f}  {row['device']:<7} {row['error']}"


if __name__ == "__main__":
    sys.exit(main())
