"""Speed-vs-error report of a run or a sweep directory.

    python -m l3d_app.report multirun/volsdf/<date_time> [--error psnr] [--out DIR]

Reads every ``metrics.json`` below the folder (and each job's ``.hydra/overrides.yaml``
when present), so it works for every task. Writes ``report.md``, ``report.csv`` and
``report.png`` (error against seconds, Pareto front marked) into ``--out`` (default: the
folder itself), and where the jobs have them ``report_loss.png`` (each job's training loss
against step; ``train_loss_end`` in the table) and ``report_views.png`` (each job's picture):
:mod:`l3d_app.runtime.sweep_pictures`. A sweep (``python main.py -m ...``) writes its report when it ends. By default the front is drawn on a validation figure (``val_psnr`` ...) where
every job reports one: a front chooses settings, and the test split only reports. A job is on the Pareto front when no other job is at least as fast AND at
least as accurate, and strictly better in one of the two.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from l3d_app.errors import UserError
from l3d_app.runtime.files import atomic_path

#: error figures in order of preference, and whether higher is better
ERROR_KEYS = {"psnr": True, "ssim": True, "iou": True, "f1": True, "accuracy": True,
              "chamfer": False, "chamfer_observed": False, "f1_observed": True, "center_error": False, "size_error": False,
              "subject_width_spread": False}
SIZE_KEYS = ("n_params", "n_gaussians", "n_faces", "n_points", "occupied_cells")


@dataclass
class Job:
    """One run: where it is, its overrides and its metrics."""

    path: str
    overrides: str
    metrics: Dict[str, object]


def find_jobs(root: Path) -> List[Job]:
    """All runs below ``root`` (a run directory itself counts), sorted by path."""
    root = Path(root)
    if not root.exists():
        raise UserError(f"report folder not found: {root}")
    jobs = []
    for metrics_path in sorted(root.rglob("metrics.json")):
        try:
            metrics = json.loads(metrics_path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise UserError(f"unreadable metrics file {metrics_path}: {err}") from err
        jobs.append(Job(str(metrics_path.parent.relative_to(root)) or ".",
                        _overrides(metrics_path.parent), metrics))
    if not jobs:
        raise UserError(f"no metrics.json below {root}")
    return jobs


def _overrides(run_dir: Path) -> str:
    path = run_dir / ".hydra" / "overrides.yaml"
    if not path.exists():
        return ""
    items = [line.strip()[2:] for line in path.read_text().splitlines() if line.strip().startswith("- ")]
    return " ".join(items)


def choose_error_key(jobs: Sequence[Job], requested: Optional[str] = None) -> str:
    """The error figure to plot: ``requested``, else the first known key every job has, as its
    validation figure ``val_<key>`` where every job reports that (a front picks settings, so it is
    drawn on the split that may choose; the test figure stays in the table as a column)."""
    if requested:
        if not all(_number(j.metrics.get(requested)) is not None for j in jobs):
            raise UserError(f"not every job has a numeric '{requested}' in metrics.json")
        return requested
    for key in ERROR_KEYS:
        for candidate in (f"val_{key}", key):
            if all(_number(j.metrics.get(candidate)) is not None for j in jobs):
                return candidate
    raise UserError(f"no common error figure among {', '.join(ERROR_KEYS)}; pass --error KEY")


def higher_is_better(key: str) -> bool:
    """The direction of an error figure (``val_<key>`` as ``key``); unknown keys: higher."""
    return ERROR_KEYS.get(key[4:] if key.startswith("val_") else key, True)


def _number(value) -> Optional[float]:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def pareto_front(seconds: Sequence[float], errors: Sequence[float], higher_is_better: bool) -> List[bool]:
    """For each job, whether no other job dominates it (faster-or-equal and better-or-equal,
    strictly better in one)."""
    sign = 1.0 if higher_is_better else -1.0
    score = [sign * e for e in errors]
    front = []
    for i in range(len(seconds)):
        dominated = any(
            seconds[j] <= seconds[i] and score[j] >= score[i] and (seconds[j] < seconds[i] or score[j] > score[i])
            for j in range(len(seconds)) if j != i)
        front.append(not dominated)
    return front


def build_table(jobs: Sequence[Job], error_key: str) -> List[Dict[str, object]]:
    """Rows: job, overrides, the error figures present, seconds, size, pareto flag."""
    higher = higher_is_better(error_key)
    seconds = [_number(j.metrics.get("seconds")) or float("nan") for j in jobs]
    errors = [float(j.metrics[error_key]) for j in jobs]
    front = pareto_front(seconds, errors, higher)
    error_cols = [c for k in ERROR_KEYS for c in (f"val_{k}", k) if any(_number(j.metrics.get(c)) is not None for j in jobs)]
    if error_key not in error_cols:
        error_cols.insert(0, error_key)
    size_cols = [k for k in SIZE_KEYS if any(_number(j.metrics.get(k)) is not None for j in jobs)]
    rows = []
    for job, sec, on_front in zip(jobs, seconds, front):
        row: Dict[str, object] = {"job": job.path, "overrides": job.overrides}
        for k in error_cols + size_cols:
            row[k] = job.metrics.get(k, "")
        row["seconds"] = sec
        row["pareto"] = on_front
        rows.append(row)
    return rows


def to_markdown(rows: Sequence[Dict[str, object]]) -> str:
    cols = list(rows[0])
    fmt = lambda v: f"{v:.4g}" if isinstance(v, float) else ("**yes**" if v is True else "" if v is False else str(v))  # noqa: E731
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r[c]) for c in cols) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def to_csv(rows: Sequence[Dict[str, object]]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def plot(rows: Sequence[Dict[str, object]], error_key: str, path: Path) -> None:
    """Error against seconds, Pareto front joined by a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    xs = [r["seconds"] for r in rows]
    ys = [float(r[error_key]) for r in rows]
    ax.scatter(xs, ys, c=["tab:red" if r["pareto"] else "tab:gray" for r in rows], zorder=3)
    for r, x, y in zip(rows, xs, ys):
        ax.annotate(r["job"], (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
    front = sorted((x, y) for r, x, y in zip(rows, xs, ys) if r["pareto"])
    if len(front) > 1:
        ax.plot(*zip(*front), color="tab:red", lw=1, label="Pareto front")
        ax.legend(fontsize=7)
    ax.set_xlabel("seconds (wall clock)")
    ax.set_ylabel(error_key + (" (higher is better)" if higher_is_better(error_key) else " (lower is better)"))
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def make_report(root: Path, error: Optional[str] = None, out: Optional[Path] = None) -> Dict[str, Path]:
    """Write report.md / report.csv / report.png for the runs below ``root``; return their paths."""
    from l3d_app.runtime.sweep_pictures import sweep_pictures

    jobs = find_jobs(Path(root))
    key = choose_error_key(jobs, error)
    rows = build_table(jobs, key)
    out = Path(out or root)
    extra = sweep_pictures(Path(root), jobs, out)
    if extra["loss_end"]:
        for row in rows:
            row["train_loss_end"] = extra["loss_end"].get(row["job"], "")
    paths = {"md": out / "report.md", "csv": out / "report.csv", "png": out / "report.png"}
    text = to_markdown(rows) + "".join(f"\n![{kind}]({p.name})\n" for kind, p in extra["files"].items())
    for kind, text in (("md", text), ("csv", to_csv(rows))):
        with atomic_path(paths[kind]) as tmp:
            tmp.write_text(text)
    plot(rows, key, paths["png"])
    return {**paths, **extra["files"]}


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m l3d_app.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="a run directory or a sweep directory")
    parser.add_argument("--error", help="metrics.json key to plot against seconds (default: first known)")
    parser.add_argument("--out", type=Path, help="where to write the report (default: the folder)")
    args = parser.parse_args(argv)
    try:
        paths = make_report(args.folder, args.error, args.out)
    except UserError as err:
        print(f"l3d_app.report: error: {err}", file=sys.stderr)
        return 2
    print(paths["md"].read_text(), end="")
    print(f"wrote {paths['md']}, {paths['csv']}, {paths['png']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
