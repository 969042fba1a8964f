"""The app's checks of the command line before a task starts: values against the type of the
default they replace, and the shared run / output knobs against their ranges.

Hydra parses ``iters=2.5`` as a float and ``resume=no`` as the string ``"no"``; a task that
reads them with ``int(...)`` or ``bool(...)`` would run 2 steps, or resume, without a word.
:func:`override_type_errors` compares each overridden value with the value the same key has
in the config composed without the user's value overrides (the same task, data and other
group choices), by these rules:

* default an integer (a count, a size): an integer, or a float with an integral value
  (``1e3``); not a bool, a string or a fraction;
* default a float: an integer or a float; not a bool or a string;
* default a bool: ``true`` or ``false``;
* default a non-empty list of numbers (a colour, a range, a sweep): a list of numbers, of any
  length (the task checks the length it needs);
* anything else (strings, lists of strings or lists, ``null`` defaults, keys added with
  ``+``): not checked here, the task checks its own.

``null`` is always let through (a task that cannot use it says so itself).
"""

from __future__ import annotations

from typing import Any, Iterable, List, Optional

from omegaconf import DictConfig, OmegaConf

from l3d_app.errors import UserError
from l3d_app.runtime.config_values import is_number_list, require_nonnegative, require_positive, shown

_MISSING = object()


def value_type_error(key: str, default: Any, value: Any) -> Optional[str]:
    """One line saying why ``value`` cannot replace ``default`` for ``key``, or None when it can."""
    if value is None or default is None:
        return None
    if isinstance(default, bool):
        return None if isinstance(value, bool) else f"{key} must be true or false, got {shown(value)}"
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"{key} must be an integer, got {shown(value)}"
        if isinstance(value, float) and not value.is_integer():
            return f"{key} must be an integer, got {shown(value)}"
        return None
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"{key} must be a number, got {shown(value)}"
    if is_number_list(default) and not is_number_list(value, allow_empty=True):
        return f"{key} must be a list of numbers, got {shown(value)}"
    return None


def _plain(value: Any) -> Any:
    """A config node as plain Python (a ListConfig as a list); anything else as it is."""
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def override_type_errors(cfg: DictConfig, defaults: DictConfig, keys: Iterable[str]) -> List[str]:
    """The :func:`value_type_error` lines of ``keys`` (dotted) in ``cfg`` against ``defaults``."""
    errors = []
    for key in keys:
        default, value = (_plain(OmegaConf.select(c, key, default=_MISSING)) for c in (defaults, cfg))
        if default is _MISSING or value is _MISSING:
            continue
        message = value_type_error(key, default, value)
        if message:
            errors.append(message)
    return errors


def value_override_keys(overrides: Iterable[str], groups: Iterable[str]) -> List[str]:
    """The dotted keys of Hydra's command-line value overrides (``iters=2``, ``data.root=x``).

    Group choices (``task=volsdf``, ``renderer@point_renderer=points``: their key is one of
    ``groups``), additions (``+key=``) and deletions (``~key``) are left out.
    """
    group_names = set(groups)
    keys = []
    for item in overrides:
        if item.startswith(("+", "~")) or "=" not in item:
            continue
        key = item.split("=", 1)[0]
        if key not in group_names:
            keys.append(key)
    return keys


def check_command_line_types(cfg: DictConfig) -> None:
    """Raise :class:`UserError` for the first command-line value whose type does not fit its
    default (:func:`value_type_error`). The defaults are the config composed again with the
    run's group choices and no value overrides. Outside a Hydra run, or where Hydra cannot
    compose again (a launcher's worker process), nothing is checked.
    """
    try:
        from hydra import compose
        from hydra.core.hydra_config import HydraConfig

        if not HydraConfig.initialized():
            return
        hydra_cfg = HydraConfig.get()
        choices = {group: choice for group, choice in hydra_cfg.runtime.choices.items()
                   if choice is not None and not group.startswith("hydra/")}
        keys = value_override_keys(hydra_cfg.overrides.task, choices)
        if not keys:
            return
        defaults = compose(config_name=hydra_cfg.job.config_name,
                           overrides=[f"{group}={choice}" for group, choice in choices.items()])
    except Exception:  # noqa: BLE001 -- a pre-check only: the run goes on as Hydra composed it
        return
    errors = override_type_errors(cfg, defaults, keys)
    if errors:
        raise UserError(errors[0])


RUN_KEYS_NONNEGATIVE = ("time_budget", "reserve", "mesh_reserve", "gif_frames", "turntable_size", "eval_views", "checkpoint_every")
"""Run and output knobs that many tasks share, where 0 means none / off / the default and a
negative value means nothing."""
RUN_KEYS_POSITIVE = ("fps",)


def require_run_keys(cfg) -> None:
    """Check the shared run / output knobs a task's config has (``RUN_KEYS_*``) before the task
    starts, so a bad turntable size or frame rate fails now, not after training."""
    require_nonnegative(cfg, *(k for k in RUN_KEYS_NONNEGATIVE if k in cfg))
    require_positive(cfg, *(k for k in RUN_KEYS_POSITIVE if k in cfg))
