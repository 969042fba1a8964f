"""A sweep's pictures beside its table: each job's training loss against step, and each job's picture.

The report of a sweep directory (:mod:`l3d_app.report`) adds, where its jobs have them:

- ``report_loss.png``: the ``train/loss`` scalar of every job's TensorBoard events against step, one line
  per job labelled by the overrides in which it differs from the others (:func:`varying_labels`; e.g. the
  course's loss curves per ``density.beta``), and each job's
  ``train_loss_end`` (the mean of the last tenth of its logged values) for the table;
- ``report_views.png``: each job's picture, one row per job titled by the same label: the first file of
  :data:`PICTURES` the job wrote (``test_views.png``: prediction | truth | error | depth of the test views).
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np

from l3d_app.runtime.files import atomic_path

PICTURES = ("test_views.png", "before_after.png", "views.png", "stereo.png", "normals.png")
LOSS_TAG = "train/loss"


def varying_labels(overrides: Sequence[str]) -> List[str]:
    """Each job's overrides (space-separated ``key=value`` words) less the words every job shares, in their
    order; a job left with none (or a single job) keeps its whole line."""
    words = [o.split() for o in overrides]
    shared = set.intersection(*map(set, words)) if len(words) > 1 else set()
    return [" ".join(w for w in ws if w not in shared) or " ".join(ws) for ws in words]


def loss_curve(run_dir: Path) -> Optional[Dict[str, List[float]]]:
    """``{"step": [...], "loss": [...]}`` of the run's ``train/loss`` events, or None (no events / no tag)."""
    if not any(Path(run_dir).glob("events.out.tfevents.*")):
        return None
    import logging

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    quiet, level = logging.getLogger("tensorboard"), logging.getLogger("tensorboard").level
    quiet.setLevel(logging.WARNING)           # its reader logs every file it finishes
    try:
        acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
        acc.Reload()
    finally:
        quiet.setLevel(level)
    if LOSS_TAG not in acc.Tags().get("scalars", []):
        return None
    events = acc.Scalars(LOSS_TAG)
    return {"step": [e.step for e in events], "loss": [e.value for e in events]}


def loss_at_end(curve: Dict[str, List[float]]) -> float:
    """The mean of the last tenth (at least one) of a curve's logged losses."""
    values = curve["loss"]
    tail = values[-max(1, len(values) // 10):]
    return float(np.mean(tail))


def plot_losses(curves: Dict[str, Dict[str, List[float]]], path: Path) -> None:
    """One line per labelled curve, loss on a log axis against step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for label, c in curves.items():
        ax.plot(c["step"], c["loss"], lw=1, label=label)
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    if all(v > 0 for c in curves.values() for v in c["loss"]):
        ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def job_picture(run_dir: Path) -> Optional[Path]:
    """The first of :data:`PICTURES` the run wrote, or None."""
    for name in PICTURES:
        if (Path(run_dir) / name).is_file():
            return Path(run_dir) / name
    return None


def plot_pictures(pictures: Dict[str, Path], path: Path, width_in: float = 8.0) -> None:
    """One row per labelled picture (titled by its label), stacked top to bottom."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    images = {label: plt.imread(str(p)) for label, p in pictures.items()}
    heights = [im.shape[0] / im.shape[1] * width_in + 0.3 for im in images.values()]
    fig, axes = plt.subplots(len(images), 1, figsize=(width_in, sum(heights)), dpi=120, squeeze=False,
                             gridspec_kw={"height_ratios": heights})
    for ax, (label, im) in zip(axes[:, 0], images.items()):
        ax.imshow(im)
        ax.set_title(label, fontsize=7)
        ax.axis("off")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def sweep_pictures(root: Path, jobs: Sequence, out: Path) -> Dict[str, object]:
    """Write ``report_loss.png`` and ``report_views.png`` for ``jobs`` (:class:`l3d_app.report.Job`) below
    ``root`` into ``out`` where any job has a loss curve / a picture; returns ``{"loss_end": {job path: loss},
    "files": {kind: path}}``."""
    curves, pictures, ends = {}, {}, {}
    for job, label in zip(jobs, varying_labels([job.overrides for job in jobs])):
        run_dir = Path(root) / job.path
        label = label or job.path
        curve = loss_curve(run_dir)
        if curve is not None and curve["loss"]:
            curves[label] = curve
            ends[job.path] = loss_at_end(curve)
        picture = job_picture(run_dir)
        if picture is not None:
            pictures[label] = picture
    files = {}
    if curves:
        files["loss"] = Path(out) / "report_loss.png"
        plot_losses(curves, files["loss"])
    if pictures:
        files["views"] = Path(out) / "report_views.png"
        plot_pictures(pictures, files["views"])
    return {"loss_end": ends, "files": files}
