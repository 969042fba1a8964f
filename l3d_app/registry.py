"""Registries: name -> constructor, with clear errors for unknown names and keys.

Usage::

    @RENDERERS.register("mesh")
    class MeshRenderer: ...

    renderer = RENDERERS.build({"name": "mesh", "image_size": 128})

``build`` accepts any mapping; the ``name`` key picks the entry and every other key is
passed as a keyword argument, with nested mappings / sequences turned into plain dicts /
lists (:func:`plain`). This module never imports OmegaConf: the app and the tasks hand it
their configs (a ``DictConfig`` is a ``Mapping``), and library code stays config-free. A name that is
not registered, or a key the constructor does not accept, raises :class:`UserError`
listing what is known, so a typo in a config never passes silently.
"""

from __future__ import annotations

import difflib
import inspect
from collections.abc import Mapping, Sequence
from typing import Any, Callable, Dict, Iterable, Optional

from l3d_app.errors import UserError


def _suggest(word: str, known: Iterable[str]) -> str:
    close = difflib.get_close_matches(word, list(known), n=1)
    return f" Did you mean '{close[0]}'?" if close else ""


def accepted_keywords(fn: Callable) -> Optional[set]:
    """Keyword names ``fn`` accepts, or None when it takes ``**kwargs``."""
    target = fn.__init__ if inspect.isclass(fn) else fn
    params = inspect.signature(target).parameters.values()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return None
    return {p.name for p in params if p.name != "self" and p.kind in (
        inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)}


def check_keywords(what: str, fn: Callable, kwargs: Mapping[str, Any]) -> None:
    """Raise :class:`UserError` if ``kwargs`` holds a key that ``fn`` does not accept."""
    accepted = accepted_keywords(fn)
    if accepted is None:
        return
    unknown = sorted(set(kwargs) - accepted)
    if unknown:
        key = unknown[0]
        raise UserError(
            f"unknown key '{key}' for {what}.{_suggest(key, accepted)} "
            f"Known keys: {', '.join(sorted(accepted)) or '(none)'}")


class Registry:
    """A named table of constructors (classes or factory functions)."""

    def __init__(self, kind: str):
        self.kind = kind
        self._entries: Dict[str, Callable] = {}

    def register(self, name: str) -> Callable[[Callable], Callable]:
        """Decorator registering ``fn`` under ``name`` (names are unique)."""
        def decorator(fn: Callable) -> Callable:
            if name in self._entries and self._entries[name] is not fn:
                raise KeyError(f"{self.kind} '{name}' is registered twice")
            self._entries[name] = fn
            return fn
        return decorator

    def names(self) -> list:
        return sorted(self._entries)

    def __contains__(self, name: str) -> bool:
        return name in self._entries

    def get(self, name: str) -> Callable:
        """The constructor registered as ``name``; a clear UserError otherwise."""
        if name not in self._entries:
            raise UserError(
                f"unknown {self.kind} '{name}'.{_suggest(str(name), self._entries)} "
                f"Known: {', '.join(self.names()) or '(none)'}")
        return self._entries[name]

    def build(self, cfg: Mapping[str, Any], **extra: Any) -> Any:
        """Construct the entry named by ``cfg['name']`` with the other keys as kwargs.

        ``extra`` keyword arguments (e.g. a device) are added to the config's keys.
        """
        if cfg is None or "name" not in cfg:
            raise UserError(f"a {self.kind} config needs a 'name' (known: {', '.join(self.names())})")
        kwargs = {str(k): plain(v) for k, v in cfg.items() if k != "name"}
        kwargs.update(extra)
        fn = self.get(str(cfg["name"]))
        check_keywords(f"{self.kind} '{cfg['name']}'", fn, kwargs)
        return fn(**kwargs)


def plain(value: Any) -> Any:
    """Nested mappings -> dicts and sequences -> lists (tuples stay tuples; strings and
    bytes unchanged), all the way down; other values as they are. Duck-typed: an OmegaConf ``DictConfig`` /
    ``ListConfig`` (resolved on access) becomes plain Python without importing OmegaConf."""
    if isinstance(value, Mapping):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return tuple(plain(v) for v in value)
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [plain(v) for v in value]
    return value


TASKS = Registry("task")
RENDERERS = Registry("renderer")
MODELS = Registry("model")
LOSSES = Registry("loss")
DATASETS = Registry("data source")
CAMERA_PATHS = Registry("camera path")
STRATEGIES = Registry("strategy")
SAMPLERS = Registry("sampler")          # ray-sample estimators (l3d_app/render/volume/estimators)
DENSITIES = Registry("density")         # SDF -> density / opacity modules (VolSDF, NeuS)
OPTIMIZERS = Registry("optimiser")      # optimiser + LR schedule builders (l3d_app/runtime/optim.py)
LOSS_TERMS = Registry("loss term")      # weighted, scheduled terms of a method's loss (l3d_app/losses/terms.py)
STAGES = Registry("stage")              # a method's work before and around its training loop (l3d_app/stages)
