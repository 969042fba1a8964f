"""Benchmark: PointNet, PointNet++ and DGCNN on the built-in scans (data=shape_scans), one table with seconds.

    python bench/bench_pointnet.py [--models pointnet pointnet2 dgcnn] [--seg] [--out NAME] [extra overrides...]
    flock /work/cpu.lock python bench/bench_pointnet.py threads=2

Runs ``python main.py task=pointnet_cls model=<m>`` for each model with the task's defaults (5 epochs,
best.pt chosen on the validation split, the test split read once) plus any overrides, into
outputs/<NAME>/cls_<m> (NAME: bench_pointnet) (``--seg``: also ``task=pointnet_seg`` into seg_<m>), then prints one
markdown table: val accuracy of the selected checkpoint, test accuracy (mIoU for seg), parameters,
training / test-pass / task seconds. ``--reuse`` re-reads finished runs. Run by hand; never in tests.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MODELS = ("pointnet", "pointnet2", "dgcnn")


def run(task: str, model: str, extra, reuse: bool, name: str = "bench_pointnet") -> dict:
    out = REPO / "outputs" / name / f"{task.split('_')[1]}_{model}"
    if not (reuse and (out / "metrics.json").exists()):
        cmd = [sys.executable, "main.py", f"task={task}", f"model={model}", f"hydra.run.dir={out}", *extra]
        print(" ".join(cmd[1:]), flush=True)
        subprocess.run(cmd, cwd=REPO, check=True)
    return json.loads((out / "metrics.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--seg", action="store_true", help="also pointnet_seg for each model")
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--out", default="bench_pointnet", help="the runs go to outputs/OUT/<task>_<model>")
    argv = sys.argv[1:]          # key=value words are overrides wherever they stand (not --models choices)
    extra = [w for w in argv if "=" in w and not w.startswith("-")]
    args = ap.parse_args([w for w in argv if w not in extra])
    rows = []
    for task in ("pointnet_cls",) + (("pointnet_seg",) if args.seg else ()):
        for model in args.models:
            m = run(task, model, extra, args.reuse, args.out)
            rows.append((task, model, m))
    print("| task | model | val accuracy (selected epoch) | test accuracy | test mIoU | params | train s | test pass s "
          "| task s |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for task, model, m in rows:
        miou = f"{m['miou']:.4f}" if "miou" in m else "-"
        print(f"| {task} | {model} | {m['val_accuracy']:.4f} ({m['best_epoch']:g}) | {m['accuracy']:.4f} | {miou} | "
              f"{m['n_params']:,} | {m['train_seconds']:.0f} | {m['test_seconds']:.0f} | {m['seconds']:.0f} |")


if __name__ == "__main__":
    main()
