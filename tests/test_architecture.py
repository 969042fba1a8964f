"""The house rules, checked on the source (``ast``; imports inside functions count too).

- layers: tasks -> (render, models, losses, metrics, data, diffusion) -> geometry -> runtime;
  within the middle layer only the edges in ``ALLOWED`` (data and models may render, losses
  may render and use metrics and the diffusion interface); nothing but ``app`` imports ``app``;
- no task imports another task (shared wiring goes to ``tasks/common.py`` or a
  ``tasks/*_common.py`` helper);
- omegaconf / hydra only in ``app.py`` (and its ``sweep_jobs.py``), ``main.py`` and ``tasks/``;
- every module that registers something is imported by its package's ``__init__``, so a
  registry is complete once its package is imported;
- a package's lazy public names resolve and never shadow one of its submodules.

Known violations in files other helpers own are listed in ``KNOWN`` with their owner: they
are strict xfails, so a NEW violation fails at once, and a fixed one fails too (XPASS) until
its entry is removed here.
"""

from __future__ import annotations

import ast
import importlib
import json
import subprocess
import sys
from functools import lru_cache
from pathlib import Path
from typing import Dict, Set

import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "l3d_app"
BASE = {"errors", "registry", "exports", "prompt_vocab", "aliases", "__init__"}  # below every layer
MIDDLE = {"render", "models", "losses", "metrics", "data", "diffusion", "strategies", "viewer", "stages"}
ALLOWED = {  # layer -> layers its modules may import (besides their own layer)
    "base": {"base"},
    "runtime": {"base"},
    "geometry": {"runtime", "base"},
    "render": {"geometry", "runtime", "base"},
    "metrics": {"geometry", "runtime", "base"},
    "diffusion": {"geometry", "runtime", "base"},
    "models": {"render", "geometry", "runtime", "base"},
    "data": {"render", "geometry", "runtime", "base"},
    "strategies": {"models", "render", "geometry", "runtime", "base"},  # act on a model's tensors
    "viewer": {"geometry", "runtime", "base"},  # the browser page: takes snapshot / render callables
    "losses": {"render", "metrics", "diffusion", "geometry", "runtime", "base"},  # rendering losses render
    "stages": {"models", "losses", "render", "metrics", "data", "geometry", "runtime", "base"},  # fit, schedule a model
    "pipelines": MIDDLE | {"geometry", "runtime", "base"},  # composes the middle layer for several tasks (plain arguments)
    "tasks": MIDDLE | {"pipelines", "geometry", "runtime", "base"},
    "report": {"runtime", "base"},
    "app": MIDDLE | {"tasks", "command_line", "sweep_jobs", "report", "geometry", "runtime", "base"},   # report: the sweep callback
    "command_line": {"runtime", "base"},   # the app's checks of command-line values (reads Hydra's overrides)
    "sweep_jobs": {"base"},      # the app's sweep bookkeeping (reads Hydra's job config)
}
CONFIG_LIBS = ("omegaconf", "hydra")

# (rule, module) -> owner. Remove an entry when its branch fixes it (the test then XPASSes).
KNOWN: Dict[tuple, str] = {
}


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def _is_module(name: str) -> bool:
    return name in MODULES


@lru_cache(maxsize=None)
def imports_of(module: str) -> frozenset:
    """Absolute names imported anywhere in ``module`` (top level, functions, branches);
    ``from pkg import sub`` counts ``pkg.sub`` when that is a module."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: Set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            out.add(source)
            out.update(f"{source}.{a.name}" for a in node.names if _is_module(f"{source}.{a.name}"))
    return frozenset(out)


def layer_of(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in BASE:
        return "base"
    return parts[1]


def _internal(module: str):
    return sorted(m for m in imports_of(module) if m == "l3d_app" or m.startswith("l3d_app."))


def _is_task_helper(module: str) -> bool:
    last = module.rsplit(".", 1)[-1]
    return last == "common" or last.endswith("_common") or module == "l3d_app.tasks"


def violations(rule: str, module: str) -> list:
    """The offending imports of ``module`` under ``rule`` (empty: it obeys)."""
    if rule == "layers":
        own = layer_of(module)
        allowed = ALLOWED[own] | {own}
        return [m for m in _internal(module) if m != "l3d_app" and layer_of(m) not in allowed]
    if rule == "no_task_imports_task":
        if layer_of(module) != "tasks" or module == "l3d_app.tasks":
            return []
        return [m for m in _internal(module) if layer_of(m) == "tasks" and m != module
                and not _is_task_helper(m)]
    if rule == "config_libs_only_at_the_top":
        if layer_of(module) in ("tasks", "app", "sweep_jobs", "command_line"):
            return []
        return [m for m in imports_of(module) if m.split(".")[0] in CONFIG_LIBS]
    raise KeyError(rule)


RULES = ("layers", "no_task_imports_task", "config_libs_only_at_the_top")
CASES = [pytest.param(rule, mod, id=f"{rule}:{mod}",
                      marks=[pytest.mark.xfail(strict=True, reason=f"known, owner: {KNOWN[(rule, mod)]}")]
                      if (rule, mod) in KNOWN else [])
         for rule in RULES for mod in MODULES]


@pytest.mark.parametrize("rule, module", CASES)
def test_module_obeys_the_house_rules(rule, module):
    bad = violations(rule, module)
    assert not bad, f"{module} breaks '{rule}' by importing {bad}"


def test_known_list_names_real_modules():
    assert all(mod in MODULES and rule in RULES for rule, mod in KNOWN)


def test_the_checker_sees_imports_inside_functions_and_relative_ones(tmp_path, monkeypatch):
    """A lazy upward import hidden in a function, and a relative one, are both caught."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from l3d_app.render.mesh.renderer import MeshRenderer\n"
                     "from ..tasks import common\n")
    monkeypatch.setitem(MODULES, "l3d_app.geometry.probe", probe)
    imports_of.cache_clear()
    try:
        bad = set(violations("layers", "l3d_app.geometry.probe"))
    finally:
        imports_of.cache_clear()
    assert {"l3d_app.render.mesh.renderer", "l3d_app.tasks", "l3d_app.tasks.common"} <= bad


def test_omegaconf_is_not_imported_by_library_code():
    """grep-equivalent of the issue's check: omegaconf appears only in the app (app.py, its command-line
    checks) and tasks/."""
    users = {m for m in MODULES if any(i.split(".")[0] == "omegaconf" for i in imports_of(m))}
    assert users <= {"l3d_app.app", "l3d_app.command_line"} | {m for m in users if layer_of(m) == "tasks"}, users


# ----------------------------------------------------------------- registration
def _registers(module: str) -> bool:
    """True when the module calls ``<REGISTRY>.register(...)`` (as a decorator or directly)."""
    tree = ast.parse(MODULES[module].read_text())
    return any(isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "register"
               and isinstance(n.func.value, ast.Name) and n.func.value.id.isupper()
               for n in ast.walk(tree))


REGISTERING = sorted(m for m in MODULES if layer_of(m) not in ("base",) and _registers(m))


def test_some_modules_register():
    assert {"l3d_app.tasks.render360", "l3d_app.data.scenes", "l3d_app.geometry.camera_paths",
            "l3d_app.render.mesh.renderer"} <= set(REGISTERING)


@pytest.mark.parametrize("module", REGISTERING)
def test_registering_module_is_imported_by_its_package(module):
    package = module.rpartition(".")[0]
    assert module in imports_of(package), (
        f"{module} registers entries but {package}/__init__.py does not import it: "
        f"add it to the package's registering imports")


def test_importing_each_package_completes_its_registries():
    """In a fresh interpreter, after ``import l3d_app.<pkg>`` (bottom-up), every registering
    module of that package is loaded, and every conf/task/*.yaml names a registered task."""
    packages = ["runtime", "geometry", "render", "metrics", "diffusion", "losses", "models", "strategies", "data", "stages",
                "tasks"]
    code = ("import importlib, json, sys\nout = {}\n"
            f"for p in {packages!r}:\n"
            "    importlib.import_module('l3d_app.' + p)\n"
            "    out[p] = sorted(m for m in sys.modules if m.startswith('l3d_app.'))\n"
            "from l3d_app.registry import TASKS\nout['tasks_registered'] = TASKS.names()\n"
            "print(json.dumps(out))\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    loaded = json.loads(res.stdout.strip().splitlines()[-1])
    for module in REGISTERING:
        package = module.split(".")[1]
        assert module in loaded[package], f"import l3d_app.{package} does not load {module}"
    import yaml

    names = {yaml.safe_load(p.read_text()).get("task_name") for p in (REPO / "conf" / "task").glob("*.yaml")}
    assert names - {None} <= set(loaded["tasks_registered"])


# ----------------------------------------------------------------- public API
PACKAGES = sorted(m for m, p in MODULES.items() if p.name == "__init__.py" and m.count(".") == 1)


@pytest.mark.parametrize("package", PACKAGES)
def test_public_names_resolve_and_do_not_shadow_submodules(package):
    mod = importlib.import_module(package)
    exported = list(getattr(mod, "__all__", []))
    submodules = {m.rsplit(".", 1)[-1] for m in MODULES if m.startswith(package + ".")}
    assert not set(exported) & submodules, f"{package} exports names of its submodules"
    for name in exported:
        assert getattr(mod, name) is not None
        assert name in dir(mod)
    with pytest.raises(AttributeError):
        getattr(mod, "no_such_name_anywhere")
