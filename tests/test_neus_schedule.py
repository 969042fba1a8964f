"""NeuS's inverse scale ``s``: fixed, learnable or annealed geometrically (as VolSDF's beta), and where a
NeuS silhouette lies: on the zero level set (float64 against the definition)."""

import math

import pytest
import torch

from l3d_app.registry import DENSITIES
from l3d_app.render.sdf.densities import transition_width
from l3d_app.render.sdf.neus import NeuSDensity


def test_anneal_is_geometric_from_s_to_s_end_then_held():
    dens = NeuSDensity(s=4.0, mode="anneal", s_end=400.0, anneal_fraction=0.5)
    expected = {0: 4.0, 25: 4.0 * 100 ** 0.5, 50: 400.0, 90: 400.0}      # iters 100: the anneal ends at step 50
    for step, s in expected.items():
        dens.schedule(step, 100)
        assert dens.s == pytest.approx(s, rel=1e-12)
        assert math.exp(float(dens.log_s)) == pytest.approx(s, rel=1e-6)     # the buffer a checkpoint keeps
        assert transition_width(dens) == pytest.approx(1.0 / s, rel=1e-12)
        assert dens.stats() == {"s": pytest.approx(s, rel=1e-12)}
    dens.schedule(12.5, 100)                   # a time-budgeted run's fractional nominal step
    assert dens.s == pytest.approx(4.0 * 100 ** 0.25, rel=1e-12)


def test_the_annealed_s_sets_the_opacity_of_a_segment():
    """A segment from f = 0.05 to f = -0.05: tau = log sigmoid(s 0.05) - log sigmoid(-s 0.05) = s 0.05 exactly."""
    dens = NeuSDensity(s=10.0, mode="anneal", s_end=1000.0, anneal_fraction=1.0)
    f = torch.tensor([0.05, -0.05], dtype=torch.float64)
    t = torch.tensor([0.0, 0.1], dtype=torch.float64)
    rays = torch.zeros(2, dtype=torch.long)
    for step, s in ((0, 10.0), (50, 100.0), (100, 1000.0)):
        dens.schedule(step, 100)
        tau = dens.optical_depth(f, t, t + 0.1, rays)
        torch.testing.assert_close(tau, torch.tensor([s * 0.05, 0.0], dtype=torch.float64), rtol=1e-9, atol=0)


def test_fixed_and_learnable_keep_their_s_through_the_schedule():
    fixed = NeuSDensity(s=64.0)
    fixed.schedule(500, 1000)
    assert fixed.s == 64.0 and not list(fixed.parameters())
    learn = NeuSDensity(s=64.0, mode="learnable")
    learn.schedule(500, 1000)
    (p,) = list(learn.parameters())
    assert float(learn.s.detach()) == pytest.approx(64.0, rel=1e-6) and p.requires_grad
    # d tau / d log s for the segment 0.05 -> -0.05: tau = 0.05 s, so 0.05 s
    tau = learn.optical_depth(torch.tensor([0.05, -0.05]), torch.tensor([0.0, 0.1]), torch.tensor([0.1, 0.2]),
                              torch.zeros(2, dtype=torch.long))
    tau.sum().backward()
    assert float(p.grad) == pytest.approx(0.05 * 64.0, rel=1e-4)


def test_an_annealed_s_survives_a_state_dict_round_trip():
    a = NeuSDensity(s=4.0, mode="anneal", s_end=400.0)
    a.schedule(400, 1000)
    b = NeuSDensity(s=4.0, mode="anneal", s_end=400.0)
    b.load_state_dict(a.state_dict())
    b.schedule(400, 1000)
    assert b.s == pytest.approx(a.s, rel=1e-12)


@pytest.mark.parametrize("kwargs,message", [
    ({"mode": "cosine"}, "fixed, learnable or anneal"),
    ({"mode": "anneal", "s_end": -1.0}, "needs s_end > 0"),
    ({"s": 0.0}, "s must be > 0"),
    ({"anneal_fraction": 1.5}, r"anneal_fraction must be in \[0, 1\]"),
])
def test_bad_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        NeuSDensity(**kwargs)


def test_the_task_config_builds_an_annealed_neus(compose):
    cfg = compose("task=volsdf", "density=neus", "s=3.0", "density.mode=anneal", "density.s_end=300",
                  "density.anneal_fraction=0.5")
    dens = DENSITIES.build(cfg.density)
    assert (dens.mode, dens.s_start, dens.s_end, dens.anneal_fraction) == ("anneal", 3.0, 300.0, 0.5)
    assert DENSITIES.build(compose("task=volsdf", "density=neus").density).mode == "fixed"


def _tau_past_a_sphere_float64(h: float, s: float, radius: float = 0.5, n: int = 20001) -> float:
    """NeuS optical depth of a ray passing a sphere at height ``h`` above it, densely sampled, written
    from the definition max(log Phi(f_i) - log Phi(f_{i+1}), 0) with Phi = 1 / (1 + exp(-s x))."""
    t = torch.linspace(-2.0, 2.0, n, dtype=torch.float64)
    f = torch.sqrt(t ** 2 + (radius + h) ** 2) - radius
    log_phi = -torch.log1p(torch.exp(-s * f))
    return float((log_phi[:-1] - log_phi[1:]).clamp_min(0).sum())


@pytest.mark.parametrize("s", [50.0, 200.0])
def test_a_neus_silhouette_lies_on_the_zero_level_set(s):
    """A ray passing at height h collects log(1 + exp(-s h)) (up to the start's own term): opacity
    1 - 1 / (1 + exp(-s h)) = 1 / (1 + exp(s h)): one half exactly at h = 0, below it outside. VolSDF's
    Laplace density at beta = 1 / s puts opacity 0.5 a few beta OUTSIDE the sphere."""
    dens = NeuSDensity(s=s)
    for h in (-0.5 / s, 0.0, 1.0 / s, 3.0 / s):
        t = torch.linspace(-2.0, 2.0, 20001, dtype=torch.float64)
        f = torch.sqrt(t ** 2 + (0.5 + h) ** 2) - 0.5
        tau = dens.optical_depth(f, t, t + 4.0 / 20000, torch.zeros_like(t, dtype=torch.long)).sum()
        assert float(tau) == pytest.approx(_tau_past_a_sphere_float64(h, s), rel=1e-9)
        opacity = 1 - math.exp(-float(tau))       # entering (h < 0) too: 1 - Phi(h) / Phi(f_start)
        assert opacity == pytest.approx(1 / (1 + math.exp(s * h)), abs=2e-3)


@pytest.mark.parametrize("override, owner", [("beta=0.1", "volsdf"), ("alpha=50", "volsdf"), ("s=200", "neus")])
def test_a_densitys_shorthand_is_refused_under_the_other(compose, override, owner):
    """``beta=``, ``alpha=``, ``s=`` stand for ``density.<key>`` (l3d_app/aliases.py): under the density that owns
    the key they set it; under the other one the key does not exist and composing fails, naming it."""
    from hydra.errors import ConfigCompositionException
    other = "neus" if owner == "volsdf" else "volsdf"
    key, value = override.split("=")
    assert compose("task=volsdf", f"density={owner}", override).density[key] == float(value)
    with pytest.raises(ConfigCompositionException, match=f"density.{key}"):
        compose("task=volsdf", f"density={other}", override)


@pytest.mark.parametrize("override", ["beta=0.1", "density.mode=fixed", "density.beta_end=0.002"])
def test_density_auto_takes_volsdfs_width_knobs_for_both(compose, override):
    """Under the default ``density=auto`` VolSDF's width knobs drive both densities (NeuS: s = 1 / beta)."""
    from l3d_app.render.sdf.density_choice import possible_configs
    cfg = compose("task=volsdf", override)
    assert cfg.density.name == "auto" and len(possible_configs(cfg.density)) == 2


def test_density_auto_refuses_what_only_one_density_reads(compose):
    """NeuS's ``s`` is not an auto knob (composing fails); VolSDF's fixed ``alpha`` would hold for one of the two
    densities only: refused before the data is read."""
    from hydra.errors import ConfigCompositionException
    from l3d_app.errors import UserError
    from l3d_app.render.sdf.density_choice import possible_configs
    with pytest.raises(ConfigCompositionException):
        compose("task=volsdf", "s=200")
    with pytest.raises(UserError, match="alpha=50 is VolSDF.s alone"):
        possible_configs(compose("task=volsdf", "alpha=50").density)


def test_a_loaded_annealed_state_renders_with_its_last_s():
    """An annealed run's checkpoint holds its last ``s`` (log_s): a fresh module of the same config loading
    it must use that ``s`` (its optical depths equal the saved module's), not the configured start."""
    from l3d_app.render.sdf.neus import NeuSDensity
    trained = NeuSDensity(s=3.0, mode="anneal", s_end=300.0, anneal_fraction=0.5)
    trained.schedule(1000, 1000)
    loaded = NeuSDensity(s=3.0, mode="anneal", s_end=300.0, anneal_fraction=0.5)
    assert loaded.s == pytest.approx(3.0)
    loaded.load_state_dict(trained.state_dict())
    assert loaded.s == pytest.approx(300.0, rel=1e-6) and loaded.stats()["s"] == pytest.approx(300.0, rel=1e-6)
    f = torch.linspace(0.05, -0.05, 11, dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    rays = torch.zeros(11, dtype=torch.long)
    torch.testing.assert_close(loaded.optical_depth(f, t, t + 0.1, rays), trained.optical_depth(f, t, t + 0.1, rays))
    fixed = NeuSDensity(s=64.0)
    fixed.load_state_dict(NeuSDensity(s=64.0).state_dict())
    assert fixed.s == pytest.approx(64.0)                   # a fixed s stays itself
    learnt = NeuSDensity(s=5.0, mode="learnable")
    with torch.no_grad():
        learnt.log_s.fill_(math.log(40.0))
    fresh = NeuSDensity(s=5.0, mode="learnable")
    fresh.load_state_dict(learnt.state_dict())
    assert float(fresh.s.detach()) == pytest.approx(40.0)
