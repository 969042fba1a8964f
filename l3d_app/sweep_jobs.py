"""A sweep (``python main.py -m ...``) goes on past a job with bad input.

A single run with bad input prints one line and exits with status 2 (:func:`l3d_app.app.run`).
Inside a sweep that exit would end the whole sweep at the first bad job, the later ones never
run. So a sweep job with bad input prints its line, labelled with the job's number and
overrides, and raises :class:`SweepJobFailed`: Hydra records the job as failed and launches
the rest; when the sweep is over Hydra raises the first failure and ``main.py`` prints one
summary line and exits with status 2. A sweep in which every job failed leaves no sweep
directory behind (nothing but Hydra's ``multirun.yaml`` was written).

A sweep's objective that a job's finished run refuses (not one of the task's metrics, or a test
figure where the task reports validation figures) is refused for the sweep's later jobs of the same
task before they run: one line each naming the job that found it, no folder, no hours spent on runs
whose value the sweeper could not take.

The record of failed jobs is per process: with the default (sequential) launcher it lists
every failed job; with a parallel launcher (joblib) the jobs run in worker processes, so the
summary names the first failure Hydra reports and the workers print their own lines.
"""

from __future__ import annotations

import contextlib
import shutil
import sys
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

from l3d_app.errors import UserError


class SweepJobFailed(UserError):
    """A sweep job that stopped on bad input; its one line is already printed."""


_failed: List[str] = []
_failed_overrides: List[List[str]] = []
_sweep_dirs: List[Path] = []
_refused_objectives: Dict[Tuple[str, str], str] = {}


def sweep_job_label() -> Optional[str]:
    """``"sweep job #N (overrides)"`` when this process runs a job of a Hydra sweep, else None."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode
    except ImportError:
        return None
    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    if hc.mode != RunMode.MULTIRUN:
        return None
    if Path(hc.sweep.dir) not in _sweep_dirs:
        _sweep_dirs.append(Path(hc.sweep.dir))
    return f"sweep job #{hc.job.num} ({' '.join(hc.overrides.task)})"


def record_failed_job(line: str) -> SweepJobFailed:
    """Remember a failed job's line (for the summary) and return the exception to raise."""
    from hydra.core.hydra_config import HydraConfig

    _failed.append(line)
    _failed_overrides.append(list(HydraConfig.get().overrides.task))
    return SweepJobFailed(line)


def remember_refused_objective(task: str, objective: str, job: str) -> None:
    """Note that ``job`` (a :func:`sweep_job_label`) of this process ran ``task`` and then had its
    ``objective`` refused (not a metric of the task, or a test figure): the sweep's later jobs of the
    same task would run to the same refusal."""
    _refused_objectives.setdefault((str(task), str(objective)), job.split(" (", 1)[0])


def refused_objective(task: str, objective: str) -> Optional[str]:
    """The earlier job of this process (``"sweep job #N"``) whose run of ``task`` had ``objective``
    refused, or None: a later job of the sweep is then refused before it runs, not after."""
    return _refused_objectives.get((str(task), str(objective)))


def failed_jobs() -> List[str]:
    """The lines of the sweep jobs that failed in this process, in launch order."""
    return list(_failed)


def summary_line(first: SweepJobFailed, none_ran: bool) -> str:
    """The sweep's closing line: how many jobs stopped on bad input and which (the first one
    Hydra reported when the jobs ran in other processes); ``none_ran``: no job wrote anything."""
    jobs = failed_jobs() or [str(first)]
    names = ", ".join(line.split(" (", 1)[0].replace("sweep job ", "") for line in jobs)
    rest = "no job ran, no sweep directory left" if none_ran else "the other jobs ran to the end"
    return f"{len(jobs)} sweep job{'s' if len(jobs) > 1 else ''} stopped on bad input ({names}: the lines above); {rest}"


def remove_empty_sweep_dirs() -> bool:
    """Remove a sweep directory that holds nothing but Hydra's ``multirun.yaml`` (every job
    failed); True when one was removed."""
    removed = False
    for path in _sweep_dirs:
        if path.is_dir() and {p.name for p in path.iterdir()} <= {"multirun.yaml"}:
            shutil.rmtree(path, ignore_errors=True)
            removed = True
    return removed


class _WithoutJobErrorEcho:
    """stderr less Hydra's "Error executing job with overrides: [...]" for a job whose own line
    is already printed (Hydra echoes the first failed job when it raises its error)."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        if any(text.startswith(f"Error executing job with overrides: {o}") for o in _failed_overrides):
            return len(text)
        return self._stream.write(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def without_job_error_echo() -> Iterator[None]:
    """Within: Hydra's echo of a failed job that printed its own line is dropped from stderr."""
    stream = sys.stderr
    sys.stderr = _WithoutJobErrorEcho(stream)
    try:
        yield
    finally:
        sys.stderr = stream
