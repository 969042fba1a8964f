"""Command-line shorthands: ``beta=0.1`` for ``density.beta=0.1`` under ``task=volsdf``.

A config value has one owner, its config group (``density.beta`` lives in conf/density/volsdf.yaml); a
task may offer a top-level shorthand for a value its users turn often. :data:`ALIASES` is the one table
of them, applied to the command line before Hydra composes (``main.py``): each ``KEY=VALUE`` whose key is
a shorthand of the task named by ``task=`` (or by the ``experiment=`` chosen, whose yaml overrides
``/task``) becomes ``TARGET=VALUE``, sweeps included (``-m task=volsdf beta=0.02,0.05`` and
``-m experiment=course_volsdf beta=0.02,0.05`` sweep ``density.beta``). A shorthand the chosen group lacks
(``s=`` with ``density=volsdf``) fails as any unknown key does.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Sequence

ALIASES: Dict[str, Dict[str, str]] = {
    "volsdf": {"beta": "density.beta", "alpha": "density.alpha", "s": "density.s"},
}
"""task -> {shorthand: the dotted key it stands for}."""

CONF = Path(__file__).resolve().parents[1] / "conf"


def experiment_task(name: str, conf: Path = CONF, depth: int = 8) -> Optional[str]:
    """The task an experiment runs: the ``override /task: NAME`` of ``conf/experiment/<name>.yaml``'s defaults
    list, or of an experiment it includes (a plain entry of that list, followed ``depth`` deep); None when there
    is none (the command line's ``task=`` then counts)."""
    path = Path(conf) / "experiment" / f"{name}.yaml"
    if depth < 0 or not path.is_file():
        return None
    import yaml

    doc = yaml.safe_load(path.read_text()) or {}
    entries = doc.get("defaults", []) if isinstance(doc, dict) else []
    for entry in entries:
        if isinstance(entry, dict):
            for key, value in entry.items():
                if str(key).replace("override", "").strip() == "/task":
                    return str(value)
    for entry in entries:
        if isinstance(entry, str) and entry != "_self_":
            task = experiment_task(entry.strip("/").split("/")[-1], conf, depth - 1)
            if task is not None:
                return task
    return None


def expand_aliases(overrides: Sequence[str], aliases: Dict[str, Dict[str, str]] = ALIASES,
                   conf: Path = CONF) -> List[str]:
    """``overrides`` (command-line words) with each shorthand of the task they choose rewritten to its
    target. The task is the one the last ``experiment=`` runs (:func:`experiment_task`), else the last
    ``task=``; a sweep over several (``task=a,b``, ``experiment=a,b``) rewrites only a shorthand every one
    of them has, to one target. Other words (flags, ``+key=``, group choices) are kept as they are."""
    def last(key: str) -> List[str]:
        words = [w.split("=", 1)[1] for w in overrides if w.startswith(f"{key}=")]
        return [t.strip() for t in words[-1].split(",")] if words else []

    experiments = [experiment_task(name, conf) for name in last("experiment")]
    names = experiments if experiments and None not in experiments else last("task")
    tables = [aliases.get(name, {}) for name in names]
    out = []
    for word in overrides:
        key, eq, value = word.partition("=")
        targets = {table.get(key) for table in tables}
        if eq and tables and len(targets) == 1 and None not in targets:
            word = f"{targets.pop()}={value}"
        out.append(word)
    return out
