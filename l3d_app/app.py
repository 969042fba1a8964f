"""The application entry: a composed Hydra config in, a finished run out.

``main.py`` hands the config to :func:`run`. Everything user-facing that can go wrong
before or during a task (a missing value, an unknown registry name, a bad file, a bad
size) reaches the app as a ``ValueError`` / ``TypeError`` (library code raises those;
:class:`~l3d_app.errors.UserError` is a ``ValueError``) or an OmegaConf config error, and
is printed on one line, exit status 2, no traceback. ``L3D_DEBUG=1`` shows the traceback.

The registries fill on import: each package imports its registering modules
(:func:`load_registries`), so no hand-kept list of modules exists.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import sys
from pathlib import Path
from typing import Any, Dict, Iterator, Optional

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from l3d_app.aliases import ALIASES
from l3d_app.command_line import check_command_line_types, require_run_keys
from l3d_app.errors import UserError
from l3d_app.registry import TASKS
from l3d_app.runtime.context import RunContext
from l3d_app.runtime.device import resolve_device
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.precision import check_precision
from l3d_app.runtime.seed import seed_everything
from l3d_app.sweep_jobs import record_failed_job, refused_objective, remember_refused_objective, sweep_job_label


def run(cfg: DictConfig, out_dir: Optional[Path] = None) -> Optional[float]:
    """Run the task named by ``cfg.task_name``; return ``metrics[cfg.objective]`` if set.

    Bad input (``ValueError``, ``TypeError``, a config error) ends the process with a
    one-line message and exit status 2 (set ``L3D_DEBUG=1`` to see the traceback instead);
    in a sweep the line names the job and :class:`~l3d_app.sweep_jobs.SweepJobFailed` is
    raised instead, so Hydra goes on with the other jobs (``main.py`` exits 2 at the end);
    a run stopped by SIGINT/SIGTERM in its training loop saves its checkpoint and metrics, then
    exits with 130; stopped outside the loop (setting up, the test evaluation, the pictures)
    it exits with 130 and one line, its checkpoints so far kept.
    """
    try:
        with _sigterm_as_interrupt():
            return run_task(cfg, out_dir)
    except KeyboardInterrupt:
        if out_dir is None:
            remove_unused_run_dir()
        print("l3d_app: interrupted outside the training loop (setting up, or evaluating and writing after it); "
              "a checkpoint written so far stays in the run directory (rerun with resume=true to continue)",
              file=sys.stderr)
        sys.exit(130)
    except USER_ERRORS as err:
        if debug_enabled():
            raise
        if out_dir is None:
            remove_unused_run_dir()
        job = sweep_job_label() if out_dir is None else None
        line = one_line(err) if job is None else f"{job}: {one_line(err)}"
        print(f"l3d_app: error: {line}", file=sys.stderr)
        if job is not None:              # a sweep goes on with its other jobs (l3d_app/sweep_jobs.py)
            raise record_failed_job(line) from None
        sys.exit(2)
    except RunInterrupted as err:
        print(f"l3d_app: {err}", file=sys.stderr)
        sys.exit(130)


USER_ERRORS = (ValueError, TypeError, OmegaConfBaseException)
"""What the app reports as a user error: library code raises ValueError/TypeError for bad
input (UserError is a ValueError); OmegaConf raises its own errors for bad config keys."""


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM raises ``KeyboardInterrupt`` as SIGINT does (the training loop installs its own
    handlers for both and turns them into a clean stop; outside it, both end the run with one
    line and status 130, not a silent 143)."""
    def handler(_signum, _frame):
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:                    # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def debug_enabled() -> bool:
    """True when ``L3D_DEBUG`` is set to a non-empty value other than 0: tracebacks shown."""
    return os.environ.get("L3D_DEBUG", "").strip() not in ("", "0")


def one_line(err: BaseException) -> str:
    """The error's message on one line (OmegaConf messages span several lines)."""
    text = " ".join(str(err).split()) or type(err).__name__
    return text if isinstance(err, UserError) else f"{text} ({type(err).__name__}; L3D_DEBUG=1 shows the traceback)"


def config_error_line(err: BaseException) -> str:
    """A Hydra composition error on one line: its message (an unknown group option's list of
    available options included) and the first line of its cause (OmegaConf's reason)."""
    message = str(err).split("Config search path:")[0]          # Hydra's search path: noise here
    text = " ".join(line.strip() for line in message.splitlines() if line.strip()) or type(err).__name__
    cause = str(err.__cause__ or "").strip().splitlines()
    unknown = re.match(r"Could not override '([^']+)'\. To append to your config use \+([^ ]+)", text)
    if unknown:                                     # a key the composed config does not have
        key = unknown.group(1)
        owners = [f"{short}= stands for {key}, which the chosen {key.rsplit('.', 1)[0]} group does not have"
                  for table in ALIASES.values() for short, target in table.items() if target == key]
        hint = owners[0] if owners else f"+{unknown.group(2)} adds a new key"
        return f"unknown key '{key}' ({hint}; `python main.py task=... --cfg job` lists the keys)"
    return f"{text} ({cause[0].strip()})" if cause else text


def load_registries() -> None:
    """Import every package that registers something, so every registry is complete."""
    from l3d_app import data, diffusion, geometry, losses, models, render, strategies, tasks  # noqa: F401


class RunInterrupted(Exception):
    """A training task stopped on SIGINT/SIGTERM after writing its checkpoint and metrics."""


def run_task(cfg: DictConfig, out_dir: Optional[Path] = None) -> Optional[float]:
    """Like :func:`run` but lets :class:`UserError` and :class:`RunInterrupted` propagate."""
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise UserError(f"missing value for {missing[0]}: pass it on the command line, "
                        f"e.g. {missing[0]}=...")
    check_command_line_types(cfg)
    load_registries()
    task = TASKS.get(str(cfg.task_name))
    require_run_keys(cfg)
    objective = cfg.get("objective")
    earlier = refused_objective(str(cfg.task_name), str(objective)) if objective else None
    if earlier is not None and sweep_job_label() is not None:
        raise UserError(f"objective '{objective}' was refused after {earlier} of this sweep ran {cfg.task_name} "
                        "(its line above says why): this job is not run")
    precision = check_precision(str(cfg.get("precision", "fp32")))
    out_dir = Path(out_dir) if out_dir is not None else _hydra_output_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    threads = int(cfg.get("threads", 0) or 0) or _parallel_thread_budget()
    if threads > 0:
        torch.set_num_threads(threads)
    device = resolve_device(cfg.get("device", "auto"))
    generator = seed_everything(int(cfg.get("seed", 0)), device)
    logger = RunLogger(out_dir, enabled=bool(cfg.get("tensorboard", True)))
    ctx = RunContext(out_dir=out_dir, device=device, generator=generator, logger=logger,
                     params=_sweep_params(cfg), time_budget=float(cfg.get("time_budget", 0) or 0),
                     reserve=float(cfg.get("reserve", 0) or 0),
                     precision=precision)
    try:
        logger.text("config", "```\n" + OmegaConf.to_yaml(cfg, resolve=True) + "\n```")
        metrics = ctx.write_metrics(task(cfg, ctx) or {})
        logger.hparams(ctx.params, metrics)
        if "over_budget_seconds" in metrics:
            warning = (f"the task took {metrics['seconds']:.1f} s, {metrics['over_budget_seconds']:.1f} s over its "
                       f"time_budget of {ctx.time_budget:g} s (what follows training did not fit: "
                       "metrics.json over_budget_seconds)")
            print(f"l3d_app: warning: {warning}", file=sys.stderr)
            logger.text("budget", warning)
    except (*USER_ERRORS, KeyboardInterrupt):
        logger.discard_if_at_most(1)      # bad input (or a stop) before anything but the config was logged
        raise
    finally:
        logger.close()
    if ctx.interrupted:
        raise RunInterrupted(f"interrupted; checkpoint and metrics so far are in {out_dir} "
                             "(rerun with resume=true and the same hydra.run.dir to continue)")
    if objective:
        job = sweep_job_label()
        try:
            if objective not in metrics:
                raise UserError(f"objective '{objective}' is not a metric of this task; "
                                f"known: {', '.join(sorted(metrics))}")
            if job is not None:          # a sweeper chooses by what main.py returns
                require_choosing_objective(str(objective), metrics)
        except UserError:
            if job is not None:          # the sweep's later jobs of this task are refused before they run
                remember_refused_objective(str(cfg.task_name), str(objective), job)
            raise
        return float(metrics[objective])
    return None


def require_choosing_objective(objective: str, metrics: Dict[str, Any]) -> None:
    """A sweep's objective chooses a setting, so it must not be a test figure (the test split is read
    once, to report): where the task reports validation figures (``val_*``), the objective is one
    of them or a cost (seconds, rates, counts, sizes: :func:`is_cost_figure`)."""
    val = sorted(k for k in metrics if k.startswith("val_") and isinstance(metrics[k], (int, float)))
    if val and not objective.startswith("val_") and not is_cost_figure(objective):
        hint = f"objective=val_{objective}" if f"val_{objective}" in metrics else f"one of {', '.join(val)}"
        raise UserError(f"objective '{objective}' is not a validation figure of this task (its test figures "
                        f"report, they do not choose); a sweep optimises {hint} or a cost such as seconds "
                        "(the run's outputs are kept)")


def is_cost_figure(key: str) -> bool:
    """Whether a metrics key is a cost rather than an accuracy figure: time, rates, counts, sizes."""
    return "second" in key or key.startswith("n_") or key in ("iters", "steps")


def _parallel_thread_budget() -> int:
    """Under a parallel launcher with ``n_jobs`` (joblib), cores // n_jobs threads; else 0."""
    try:
        from hydra.core.hydra_config import HydraConfig

        n_jobs = int(HydraConfig.get().launcher.get("n_jobs", 0) or 0) if HydraConfig.initialized() else 0
    except (ImportError, ValueError, AttributeError):
        return 0
    return max(1, (os.cpu_count() or 1) // n_jobs) if n_jobs > 1 else 0


def remove_unused_run_dir() -> None:
    """After bad input: remove Hydra's run directory for this run if it holds nothing but Hydra's
    own ``.hydra`` folder and an empty ``main.log`` (nothing the run wrote, nothing resumed)."""
    try:
        run_dir = _hydra_output_dir()
    except UserError:
        return
    if not run_dir.is_dir():
        return
    entries = {p.name: p for p in run_dir.iterdir()}
    if set(entries) <= {".hydra", "main.log"} and (
            "main.log" not in entries or entries["main.log"].stat().st_size == 0):
        shutil.rmtree(run_dir, ignore_errors=True)


def _hydra_output_dir() -> Path:
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        raise UserError("no output directory: run through main.py or pass out_dir")
    return Path(HydraConfig.get().runtime.output_dir)


def _sweep_params(cfg: DictConfig) -> Dict[str, Any]:
    """The run's hyper-parameters for TensorBoard: the task, the seed and the overrides."""
    params: Dict[str, Any] = {"task": str(cfg.task_name), "seed": int(cfg.get("seed", 0))}
    try:
        from hydra.core.hydra_config import HydraConfig

        if HydraConfig.initialized():
            for item in HydraConfig.get().overrides.task:
                key, _, value = item.partition("=")
                params[key.lstrip("+~")] = _parse_scalar(value)
    except ImportError:
        pass
    return params


def _parse_scalar(text: str) -> Any:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def _hydra_callback_base():
    """Hydra's ``Callback`` base class (an ``object`` stand-in when Hydra is absent)."""
    try:
        from hydra.experimental.callback import Callback
    except ImportError:      # pragma: no cover - hydra is a dependency
        return object
    return Callback


class SweepReport(_hydra_callback_base()):
    """Hydra callback (``conf/config.yaml``: ``hydra.callbacks``): when a sweep ends, its report
    (:func:`l3d_app.report.make_report`: the speed-vs-error table, loss curves and each job's picture) is
    written into the sweep directory; a sweep whose jobs share no error figure gets one note line instead."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from l3d_app.report import make_report

        root = Path(str(config.hydra.sweep.dir))
        if not root.is_dir() or not any(root.rglob("metrics.json")):
            return
        try:
            paths = make_report(root)
        except (UserError, OSError) as err:
            print(f"l3d_app: note: no sweep report: {one_line(err)}", file=sys.stderr)
            return
        print(f"l3d_app: sweep report: {paths['md']}", file=sys.stderr)
