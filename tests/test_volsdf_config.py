"""volsdf's configuration: one owner per value. The composed config stays small, each group's yaml values are
its library's defaults (or the library has none), and the top-level shorthands (beta=, alpha=, s=) are one
alias table applied to the command line before Hydra composes (l3d_app/aliases.py)."""

import inspect
import subprocess
import sys

import pytest

from conftest import REPO
from l3d_app.aliases import ALIASES, expand_aliases
from l3d_app.registry import DENSITIES, LOSS_TERMS, MODELS, SAMPLERS, STAGES


def _leaves(node) -> int:
    """Leaves of a composed config, a list counting as one."""
    from omegaconf import DictConfig
    return sum(_leaves(v) for v in node.values()) if isinstance(node, DictConfig) else 1


def test_volsdf_composes_at_most_90_values(compose):
    from omegaconf import OmegaConf
    cfg = compose("task=volsdf")
    OmegaConf.resolve(cfg)
    assert _leaves(cfg) <= 90


def _entries(cfg):
    """(registry, entry config) of every registry-built part of a composed volsdf config."""
    yield MODELS, cfg.model
    yield SAMPLERS, cfg.sampler
    for registry, group in ((LOSS_TERMS, cfg.losses), (STAGES, cfg.stages)):
        for entry in group.values():
            yield registry, entry


@pytest.mark.parametrize("density", ["volsdf", "neus"])
def test_each_shipped_value_is_its_librarys_default(compose, density):
    """A value the yaml ships equals the default of the constructor it configures (where that has one): the
    yaml owns it, the library does not disagree."""
    import l3d_app.losses  # noqa: F401
    import l3d_app.stages  # noqa: F401
    cfg = compose("task=volsdf", f"density={density}")
    for registry, entry in [*_entries(cfg), (DENSITIES, cfg.density)]:
        params = inspect.signature(registry.get(entry.name)).parameters
        for key, value in entry.items():
            if key == "name" or params[key].default is inspect.Parameter.empty:
                continue
            assert params[key].default == value, (entry.name, key, params[key].default, value)


def test_auto_is_volsdfs_config_under_its_own_name(compose):
    auto, volsdf = compose("task=volsdf").density, compose("task=volsdf", "density=volsdf").density
    assert auto.name == "auto" and {k: v for k, v in auto.items() if k != "name"} == \
        {k: v for k, v in volsdf.items() if k != "name"}


def test_shorthands_expand_for_their_task_only():
    assert ALIASES["volsdf"]["beta"] == "density.beta"
    assert expand_aliases(["-m", "task=volsdf", "beta=0.02,0.05", "s=3", "iters=5"]) == \
        ["-m", "task=volsdf", "density.beta=0.02,0.05", "density.s=3", "iters=5"]
    assert expand_aliases(["task=box", "beta=0.05", "alpha=1.0"]) == ["task=box", "beta=0.05", "alpha=1.0"]
    assert expand_aliases(["beta=0.05"]) == ["beta=0.05"]                  # the default task has none
    assert expand_aliases(["task=volsdf,box", "beta=0.05"]) == ["task=volsdf,box", "beta=0.05"]
    assert expand_aliases(["task=volsdf", "+beta=1", "density.beta=2"]) == ["task=volsdf", "+beta=1", "density.beta=2"]


def test_the_command_line_shorthand_sets_the_density(tmp_path):
    """``python main.py task=volsdf beta=0.1``: main.py expands the shorthand (the sweep form composes alike)."""
    res = subprocess.run([sys.executable, "main.py", "task=volsdf", "beta=0.1", "--cfg", "job"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "beta: 0.1\n" in res.stdout and "\nbeta:" not in res.stdout      # under density:, not at the top


def test_a_sweep_of_the_shorthand_composes_each_value(compose):
    for beta in (0.02, 0.5):
        assert compose("task=volsdf", f"beta={beta}").density.beta == beta
