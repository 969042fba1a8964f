"""Command-line shorthands: ``beta=0.1`` for ``density.beta=0.1`` under ``task=volsdf``.

A config value has one owner, its config group (``density.beta`` lives in conf/density/volsdf.yaml); a
task may offer a top-level shorthand for a value its users turn often. :data:`ALIASES` is the one table
of them, applied to the command line before Hydra composes (``main.py``): each ``KEY=VALUE`` whose key is
a shorthand of the task named by ``task=`` becomes ``TARGET=VALUE``, sweeps included (``-m task=volsdf
beta=0.02,0.05`` sweeps ``density.beta``). A shorthand the chosen group lacks (``s=`` with
``density=volsdf``) fails as any unknown key does.
"""

from __future__ import annotations

from typing import Dict, List, Sequence

ALIASES: Dict[str, Dict[str, str]] = {
    "volsdf": {"beta": "density.beta", "alpha": "density.alpha", "s": "density.s"},
}
"""task -> {shorthand: the dotted key it stands for}."""


def expand_aliases(overrides: Sequence[str], aliases: Dict[str, Dict[str, str]] = ALIASES) -> List[str]:
    """``overrides`` (command-line words) with each shorthand of the ``task=`` they name rewritten to its
    target; a sweep over several tasks (``task=a,b``) rewrites only a shorthand every one of them has,
    to one target. Other words (flags, ``+key=``, group choices) are kept as they are."""
    tasks = [w.split("=", 1)[1] for w in overrides if w.startswith("task=")]
    names = [t.strip() for t in tasks[-1].split(",")] if tasks else []
    tables = [aliases.get(name, {}) for name in names]
    out = []
    for word in overrides:
        key, eq, value = word.partition("=")
        targets = {table.get(key) for table in tables}
        if eq and tables and len(targets) == 1 and None not in targets:
            word = f"{targets.pop()}={value}"
        out.append(word)
    return out
