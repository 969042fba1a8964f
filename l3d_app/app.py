"""The application entry: a composed Hydra config in, a finished run out.

``main.py`` hands the config to :func:`run`. Everything user-facing that can go wrong
before or during a task (a missing value, an unknown registry name, a bad file) is a
:class:`UserError`: printed on one line, exit status 2, no traceback.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Dict, Optional

import torch
from omegaconf import DictConfig, OmegaConf

from l3d_app import catalog
from l3d_app.errors import UserError
from l3d_app.registry import TASKS
from l3d_app.runtime.context import RunContext
from l3d_app.runtime.device import resolve_device
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.seed import seed_everything


def run(cfg: DictConfig, out_dir: Optional[Path] = None) -> Optional[float]:
    """Run the task named by ``cfg.task_name``; return ``metrics[cfg.objective]`` if set.

    A :class:`UserError` ends the process with a one-line message and exit status 2; a run
    stopped by SIGINT/SIGTERM saves its checkpoint and metrics, then exits with status 130.
    """
    try:
        return run_task(cfg, out_dir)
    except UserError as err:
        print(f"l3d_app: error: {err}", file=sys.stderr)
        sys.exit(2)
    except RunInterrupted as err:
        print(f"l3d_app: {err}", file=sys.stderr)
        sys.exit(130)


class RunInterrupted(Exception):
    """A training task stopped on SIGINT/SIGTERM after writing its checkpoint and metrics."""


def run_task(cfg: DictConfig, out_dir: Optional[Path] = None) -> Optional[float]:
    """Like :func:`run` but lets :class:`UserError` and :class:`RunInterrupted` propagate."""
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise UserError(f"missing value for {missing[0]}: pass it on the command line, "
                        f"e.g. {missing[0]}=...")
    catalog.load_all()
    task = TASKS.get(str(cfg.task_name))
    out_dir = Path(out_dir) if out_dir is not None else _hydra_output_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    threads = int(cfg.get("threads", 0) or 0) or _parallel_thread_budget()
    if threads > 0:
        torch.set_num_threads(threads)
    device = resolve_device(cfg.get("device", "auto"))
    generator = seed_everything(int(cfg.get("seed", 0)), device)
    logger = RunLogger(out_dir, enabled=bool(cfg.get("tensorboard", True)))
    ctx = RunContext(out_dir=out_dir, device=device, generator=generator, logger=logger,
                     params=_sweep_params(cfg))
    try:
        logger.text("config", "```\n" + OmegaConf.to_yaml(cfg, resolve=True) + "\n```")
        metrics = ctx.write_metrics(task(cfg, ctx) or {})
        logger.hparams(ctx.params, metrics)
    finally:
        logger.close()
    if ctx.interrupted:
        raise RunInterrupted(f"interrupted; checkpoint and metrics so far are in {out_dir} "
                             "(rerun with resume=true and the same hydra.run.dir to continue)")
    objective = cfg.get("objective")
    if objective:
        if objective not in metrics:
            raise UserError(f"objective '{objective}' is not a metric of this task; "
                            f"known: {', '.join(sorted(metrics))}")
        return float(metrics[objective])
    return None


def _parallel_thread_budget() -> int:
    """Under a parallel launcher with ``n_jobs`` (joblib), cores // n_jobs threads; else 0."""
    try:
        from hydra.core.hydra_config import HydraConfig

        n_jobs = int(HydraConfig.get().launcher.get("n_jobs", 0) or 0) if HydraConfig.initialized() else 0
    except (ImportError, ValueError, AttributeError):
        return 0
    return max(1, (os.cpu_count() or 1) // n_jobs) if n_jobs > 1 else 0


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
