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
    old = NeuSDensity(s=64.0, learnable=True)                  # the older spelling
    assert old.mode == "learnable" and len(list(old.parameters())) == 1
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
    ({"mode": "anneal"}, "needs s_end > 0"),
    ({"mode": "anneal", "s_end": -1.0}, "needs s_end > 0"),
    ({"s": 0.0}, "s must be > 0"),
    ({"anneal_fraction": 1.5}, r"anneal_fraction must be in \[0, 1\]"),
])
def test_bad_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        NeuSDensity(**kwargs)


def test_the_task_config_builds_an_annealed_neus(compose):
    cfg = compose("task=volsdf", "density=neus", "s=3.0", "s_mode=anneal", "s_end=300", "anneal_fraction=0.5")
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
    Laplace density at beta = 1 / s puts opacity 0.5 a few beta OUTSIDE the sphere (tasks/volsdf.py)."""
    dens = NeuSDensity(s=s)
    for h in (-0.5 / s, 0.0, 1.0 / s, 3.0 / s):
        t = torch.linspace(-2.0, 2.0, 20001, dtype=torch.float64)
        f = torch.sqrt(t ** 2 + (0.5 + h) ** 2) - 0.5
        tau = dens.optical_depth(f, t, t + 4.0 / 20000, torch.zeros_like(t, dtype=torch.long)).sum()
        assert float(tau) == pytest.approx(_tau_past_a_sphere_float64(h, s), rel=1e-9)
        opacity = 1 - math.exp(-float(tau))       # entering (h < 0) too: 1 - Phi(h) / Phi(f_start)
        assert opacity == pytest.approx(1 / (1 + math.exp(s * h)), abs=2e-3)


def _stops_with(compose, match, *overrides):
    """volsdf on a missing folder with ``overrides`` raises a UserError matching ``match`` (a refused knob) or
    naming the folder (the knobs accepted: the run got as far as the data)."""
    import l3d_app.tasks  # noqa: F401
    from l3d_app.errors import UserError
    from l3d_app.registry import TASKS
    cfg = compose("task=volsdf", *overrides, "data=blender", "data.root=/no/such/folder")
    with pytest.raises(UserError, match=match):
        TASKS.get("volsdf")(cfg, None)


@pytest.mark.parametrize("override, owner", [
    *[(o, "volsdf") for o in ("density_along_ray=true", "quadrature=linear", "alpha=50", "beta=0.1",
                              "beta_mode=learnable", "beta_end=0.002", "beta_min=0.0005")],
    *[(o, "neus") for o in ("s=200", "s_mode=learnable", "s_end=500")]])
def test_a_densitys_own_knob_is_refused_under_the_other(compose, override, owner):
    """``density=neus beta=0.1`` or ``density=volsdf s=200`` would be ignored: refused, naming the density the
    knob needs; under that density the same knob is accepted (the run stops at the missing data)."""
    other = "neus" if owner == "volsdf" else "volsdf"
    _stops_with(compose, f"needs density={owner}, got density={other}", f"density={other}", override)
    _stops_with(compose, "/no/such/folder", f"density={owner}", override)


def test_the_refused_knobs_shipped_values_are_the_configs(compose):
    """The check compares each knob with the value conf/task/volsdf.yaml ships: the two must agree, or a
    default run of either density would be refused (or a changed knob let through)."""
    from l3d_app.tasks.volsdf import NEUS_ONLY, VOLSDF_ONLY
    cfg = compose("task=volsdf")
    for key, shipped in {**VOLSDF_ONLY, **NEUS_ONLY}.items():
        assert cfg.get(key) == shipped, key


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


@pytest.mark.parametrize("override,accepted", [("beta=0.1", True), ("beta_mode=fixed", True), ("beta_end=0.002", True),
                                               ("s=200", False), ("s_mode=learnable", False), ("quadrature=linear", False),
                                               ("alpha=50", False), ("beta_min=0.0005", False),
                                               ("density_along_ray=true", False)])
def test_density_auto_takes_the_shared_width_knobs_and_refuses_one_densitys_own(compose, override, accepted):
    """Under the default ``density=auto`` beta / beta_mode / beta_end drive both densities (NeuS: s = 1 / beta);
    a knob only one density reads would hold for one of the two: refused before the data is read."""
    assert compose("task=volsdf").density.name == "auto"
    _stops_with(compose, "/no/such/folder" if accepted else "got density=auto .density=auto picks NeuS or VolSDF",
                override)
