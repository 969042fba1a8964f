"""User paths: relative to where the command runs, with the repository as a fallback.

Hydra does not change the working directory here (``hydra.job.chdir=false``), so a path
the user types is read relative to their shell's directory. Built-in defaults such as
``../shared/data/box`` are written relative to the repository root; they are found there
when the working directory does not hold them.
"""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]


def resolve_path(path: os.PathLike) -> Path:
    """Absolute path for ``path``: itself if absolute; else relative to the working
    directory if it exists there; else relative to the repository root if it exists
    there; else relative to the working directory (so errors name what the user typed)."""
    p = Path(str(path)).expanduser()
    if p.is_absolute():
        return p
    for base in (Path.cwd(), REPO_ROOT):
        if (base / p).exists():
            return (base / p).resolve()
    return (Path.cwd() / p).resolve()
