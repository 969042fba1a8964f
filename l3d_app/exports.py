"""Lazy public names for the package ``__init__`` files.

Each package exports a small public API (``from l3d_app.render import MeshRenderer``) as a
table name -> defining module. A name's module is imported the first time the name is
read (PEP 562 module ``__getattr__``), so ``import l3d_app.geometry`` stays cheap and
the exports can never form an import cycle between packages; what a package must import
at once (its registering modules) it imports explicitly.
"""

from __future__ import annotations

import importlib
from typing import Callable, Dict, List, Tuple


def lazy_exports(package: str, table: Dict[str, str]) -> Tuple[Callable, Callable, List[str]]:
    """``(__getattr__, __dir__, __all__)`` for ``package`` exporting ``table``
    (public name -> module path relative to the package, e.g. ``"mesh_renderer"``)."""
    def __getattr__(name: str):
        if name not in table:
            raise AttributeError(f"module '{package}' has no attribute '{name}'")
        value = getattr(importlib.import_module(f"{package}.{table[name]}"), name)
        globals_of_package = importlib.import_module(package).__dict__
        globals_of_package[name] = value      # cache: later reads skip __getattr__
        return value

    def __dir__() -> List[str]:
        return sorted(set(importlib.import_module(package).__dict__) | set(table))

    return __getattr__, __dir__, sorted(table)
