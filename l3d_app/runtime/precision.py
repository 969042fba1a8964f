"""Mixed precision and ``torch.compile``, from plain arguments (no Hydra).

* :func:`autocast` -- ``with autocast("bf16", device): ...`` runs the block under
  ``torch.autocast(device_type, dtype=torch.bfloat16)``; ``"fp32"`` is a no-op context.
  Autocast only changes the ops on its list (matmul / linear / conv run in bf16 and return
  bf16); elementwise ops, reductions, ``exp``/``log``, cumsum and the index gathers keep
  their input dtype. Parameters stay float32, and their gradients are float32.
* :func:`maybe_compile` -- ``torch.compile`` when asked and available, with a safe fallback:
  if compilation (which happens lazily, at the first call) raises, a warning is issued once
  and the eager function is used from then on.

Measured on the project's CPU (docs/cpu_frontier.md, bench/bench_cpu_frontier.py): which
hot paths gain from bf16 or compile, and what error they cost.
"""

from __future__ import annotations

import contextlib
import importlib.util
import warnings
from typing import Any, Callable, ContextManager, Union

import torch

from l3d_app.errors import UserError

#: the precision strings a task's ``precision=`` knob accepts.
PRECISIONS = ("fp32", "bf16")
_DTYPES = {"bf16": torch.bfloat16}


def check_precision(precision: str) -> str:
    """Return ``precision`` if it is one of :data:`PRECISIONS`, else raise ValueError naming them."""
    if precision not in PRECISIONS:
        raise UserError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    return precision


def autocast(precision: str = "fp32", device: Union[str, torch.device, None] = "cpu") -> ContextManager:
    """A context manager for ``precision`` on ``device`` (``"cpu"``, ``"cuda"``, a
    ``torch.device``, or None for CPU).

    ``"fp32"``: does nothing (an enclosing autocast stays in force). ``"bf16"``:
    ``torch.autocast(device.type, dtype=torch.bfloat16)``. Anything else: ValueError.
    """
    check_precision(precision)
    if precision == "fp32":
        return contextlib.nullcontext()
    device_type = torch.device(device if device is not None else "cpu").type
    return torch.autocast(device_type, dtype=_DTYPES[precision])


def compile_available() -> bool:
    """True when this torch has ``torch.compile`` (Python versions / builds without dynamo lack it)."""
    if not hasattr(torch, "compile"):
        return False
    try:   # find, do not import (importing dynamo costs seconds)
        return importlib.util.find_spec("torch._dynamo") is not None
    except (ImportError, ValueError):  # pragma: no cover - depends on the build
        return False


class _CompiledOrEager:
    """Calls the compiled function; on the first exception from it, warns once and falls back to
    the eager one for good. Attribute access goes to the eager object (a module's parameters,
    ``state_dict``, methods ...)."""

    def __init__(self, eager: Callable, compiled: Callable):
        self.__dict__.update(eager=eager, compiled=compiled, failed=False, ran=False)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if not self.failed:
            try:
                out = self.compiled(*args, **kwargs)
                self.__dict__["ran"] = True
                return out
            except Exception as err:  # dynamo / inductor / C++ compiler failures
                if self.ran:
                    raise   # it compiled and ran before: this is a real error of the function
                warnings.warn(f"torch.compile failed ({type(err).__name__}: {str(err).splitlines()[0][:200]}); "
                              "running eagerly", RuntimeWarning, stacklevel=2)
                self.__dict__["failed"] = True
        return self.eager(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["eager"], name)


def maybe_compile(fn: Callable, enabled: bool = True, **compile_kwargs: Any) -> Callable:
    """``torch.compile(fn, **compile_kwargs)`` with a safe fallback, or ``fn`` itself.

    Args:
        fn: a function or ``torch.nn.Module``.
        enabled: False returns ``fn`` unchanged (no wrapper).
        compile_kwargs: passed to ``torch.compile`` (e.g. ``mode="max-autotune-no-cudagraphs"``,
            ``dynamic=False``).
    Returns:
        ``fn`` when disabled or when ``torch.compile`` is unavailable (with a warning); else a
        callable that runs the compiled version and, if compiling raises at the first call,
        warns and runs ``fn`` eagerly from then on. Attributes of the wrapper are ``fn``'s.
    """
    if not enabled:
        return fn
    if not compile_available():
        warnings.warn("torch.compile is not available in this torch build; running eagerly", RuntimeWarning,
                      stacklevel=2)
        return fn
    try:
        compiled = torch.compile(fn, **compile_kwargs)
    except Exception as err:  # bad kwargs, unsupported platform
        warnings.warn(f"torch.compile failed ({type(err).__name__}: {err}); running eagerly", RuntimeWarning,
                      stacklevel=2)
        return fn
    return _CompiledOrEager(fn, compiled)
