"""Densification strategies: default (3DGS), mcmc (3DGS-MCMC), course (fixed set).

Expected values are derived by hand in each test (which splats clone / split / die, the
relocation formula as the paper's double sum written with math.comb), not read off the code.
"""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.models.gaussians import PARAM_NAMES, init_from_points
from l3d_app.registry import STRATEGIES
from l3d_app.strategies.default import SPLIT_SHRINK, DefaultStrategy
from l3d_app.strategies.mcmc import MCMCStrategy, relocation


def _model_and_adam(n=20, seed=0, isotropic=False):
    g = torch.Generator().manual_seed(seed)
    m = init_from_points(torch.rand(n, 3, generator=g), isotropic=isotropic)
    opt = torch.optim.Adam([{"params": [getattr(m, k)], "name": k} for k in PARAM_NAMES], lr=1e-3)
    sum(p.sum() for p in m.parameters()).backward()
    opt.step()                                          # non-zero Adam moments everywhere
    return m, opt


def _info(grad_px, n, width=2, height=2):
    """A render's info with a screen-space gradient of ``grad_px`` (N,) NDC units along x."""
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = torch.zeros(1, n, 2)
    means2d.grad[0, :, 0] = grad_px / (0.5 * width)     # NDC norm = px grad * width / 2
    return {"means2d": means2d, "radii": torch.ones(1, n), "width": width, "height": height}


def test_strategies_are_registered():
    assert {"default", "mcmc", "course"} <= set(STRATEGIES.names())


def test_default_clones_small_splits_large_prunes_transparent_on_schedule():
    m, opt = _model_and_adam()
    m.log_scales.data[:10] = -6.0          # small (<= 0.01 * extent 1): clone
    m.log_scales.data[10:] = -1.0          # large: split (0.37 > 0.01, below max_world_scale 0.5)
    m.opacity_logits.data[19] = -10.0      # transparent: pruned
    parent_means = m.means.detach().clone()
    ls_before = m.log_scales.detach().clone()
    adam_before = opt.state[m.means]["exp_avg"].clone()
    s = DefaultStrategy(start=2, until=10, every=2, grad_threshold=0.1, max_world_scale=0.5)
    s.initialize(m, opt, scene_extent=1.0)
    grad = torch.zeros(20)
    grad[:4] = 1.0                         # 0..3 clone
    grad[10:12] = 1.0                      # 10, 11 split
    grad[4] = 0.05                         # below the threshold: nothing
    g = torch.Generator().manual_seed(0)
    assert s.step_post_backward(m, opt, 0, _info(grad, 20), g) == {}      # step 1: accumulate only
    logs = s.step_post_backward(m, opt, 1, _info(grad, 20), g)            # step 2: densify
    assert (logs["cloned"], logs["split"], logs["pruned"]) == (4, 2, 3)   # pruned: 2 parents + 1 transparent
    assert m.num == 20 + 4 + 4 - 2 - 1 == logs["n"]
    kept = [i for i in range(20) if i not in (10, 11, 19)]
    torch.testing.assert_close(m.means[:17], parent_means[kept])
    torch.testing.assert_close(m.means[17:21], parent_means[:4])          # clones: same place
    torch.testing.assert_close(opt.state[m.means]["exp_avg"][:17], adam_before[kept])
    assert torch.all(opt.state[m.means]["exp_avg"][17:] == 0)             # new splats: fresh moments
    children = m.means[21:].detach()                                       # 2 per split parent, inside it
    par = parent_means[[10, 11, 10, 11]]
    assert float((children - par).norm(dim=-1).max()) < 6 * math.exp(-1.0)
    torch.testing.assert_close(m.log_scales[21:], ls_before[[10, 11, 10, 11]] - math.log(SPLIT_SHRINK))
    assert {id(p) for gr in opt.param_groups for p in gr["params"]} == {id(p) for p in m.parameters()}
    # past `until`: nothing accumulates or changes
    n = m.num
    for step in range(10, 16):
        assert s.step_post_backward(m, opt, step, _info(torch.ones(n), n), g) == {}
    assert m.num == n


def test_default_split_of_isotropic_splats_keeps_one_scale():
    m, opt = _model_and_adam(isotropic=True)
    m.log_scales.data[:] = -1.0
    s = DefaultStrategy(start=1, every=1, grad_threshold=0.1, max_world_scale=0.0)
    s.initialize(m, opt, 1.0)
    grad = torch.zeros(20)
    grad[:3] = 1.0
    s.step_post_backward(m, opt, 0, _info(grad, 20), torch.Generator().manual_seed(1))
    assert m.num == 20 - 3 + 6 and m.log_scales.shape == (23, 1)


def test_default_cap_keeps_the_strongest_gradients():
    m, opt = _model_and_adam()
    m.log_scales.data[:] = -6.0
    s = DefaultStrategy(start=1, every=1, grad_threshold=0.1, max_gaussians=24)   # room 4 -> 2 clones
    s.initialize(m, opt, 1.0)
    grad = torch.zeros(20)
    grad[[3, 7, 9]] = torch.tensor([0.5, 2.0, 1.0])
    means = m.means.detach().clone()
    s.step_post_backward(m, opt, 0, _info(grad, 20))
    assert m.num == 22
    torch.testing.assert_close(m.means[20:], means[[7, 9]])


def test_default_opacity_reset_and_state_round_trip():
    m, opt = _model_and_adam()
    m.opacity_logits.data[:] = 3.0
    s = DefaultStrategy(start=100, every=50, opacity_reset_every=3, reset_value=0.01)
    s.initialize(m, opt, 1.0)
    for step in range(3):
        s.step_post_backward(m, opt, step, _info(torch.full((20,), 0.3), 20))
    torch.testing.assert_close(torch.sigmoid(m.opacity_logits), torch.full((20,), 0.01))
    assert torch.all(opt.state[m.opacity_logits]["exp_avg"] == 0)
    s2 = DefaultStrategy()
    s2.load_state_dict(s.state_dict())
    torch.testing.assert_close(s2.grad_accum, torch.full((20,), 0.9))      # 3 steps x 0.3


@pytest.mark.parametrize("steps_left,expect_reset", [(299, False), (300, True), (None, True)])
def test_default_opacity_reset_skipped_near_the_end(steps_left, expect_reset):
    """A reset due with fewer than reset_min_steps_left steps left would leave the run at its
    reset opacities; it is skipped then, and made when enough steps remain or nobody says."""
    m, opt = _model_and_adam()
    m.opacity_logits.data[:] = 3.0
    s = DefaultStrategy(start=100, every=50, opacity_reset_every=2, reset_min_steps_left=300)
    s.initialize(m, opt, 1.0)
    for step in range(2):
        info = _info(torch.full((20,), 0.3), 20)
        if steps_left is not None:
            info["steps_left"] = steps_left
        s.step_post_backward(m, opt, step, info)
    expected = 0.01 if expect_reset else 1 / (1 + math.exp(-3.0))
    torch.testing.assert_close(torch.sigmoid(m.opacity_logits), torch.full((20,), expected))


@pytest.mark.parametrize("steps_left,expect_growth", [(99, False), (100, True), (None, True)])
def test_default_densification_skipped_near_the_end(steps_left, expect_growth):
    """With densify_min_steps_left=100 a densification due with 99 steps left is skipped (the
    count stays 20), one with 100 left or with nobody saying is made (every splat's gradient is
    over the threshold and small: each is cloned, 40)."""
    m, opt = _model_and_adam()
    s = DefaultStrategy(start=2, until=1000, every=2, grad_threshold=0.1, max_gaussians=1000,
                        densify_min_steps_left=100)
    s.initialize(m, opt, 1000.0)
    for step in range(2):
        info = _info(torch.full((20,), 0.3), m.num)
        if steps_left is not None:
            info["steps_left"] = steps_left
        s.step_post_backward(m, opt, step, info)
    assert m.num == (40 if expect_growth else 20), m.num


def _relocation_reference(o: float, k: int):
    """The paper's eq. (9): o' = 1 - (1-o)^(1/k); s' = o / sum_{i=1..k} sum_{j<i} C(i-1,j) (-1)^j o'^(j+1)/sqrt(j+1)."""
    on = 1 - (1 - o) ** (1 / k)
    d = sum(math.comb(i - 1, j) * (-1) ** j * on ** (j + 1) / math.sqrt(j + 1)
            for i in range(1, k + 1) for j in range(i))
    return on, o / d


@pytest.mark.parametrize("o,k", [(0.3, 1), (0.9, 2), (0.05, 3), (0.5, 5), (0.99, 8), (0.7, 20)])
def test_mcmc_relocation_formula(o, k):
    new_o, new_s = relocation(torch.tensor([o]), torch.tensor([[2.0, 1.0, 0.5]]), torch.tensor([k]))
    ro, rs = _relocation_reference(o, k)
    assert abs(float(new_o) - ro) < 1e-6
    torch.testing.assert_close(new_s[0], torch.tensor([2.0, 1.0, 0.5]) * rs, rtol=1e-5, atol=1e-6)
    assert 1 - (1 - float(new_o)) ** k == pytest.approx(o, abs=1e-6)   # k copies composite to the original


def test_mcmc_relocates_dead_splats_onto_live_ones_and_respects_the_cap():
    m, opt = _model_and_adam(n=30)
    m.opacity_logits.data[:] = 2.0
    dead = torch.tensor([0, 5, 6, 29])
    m.opacity_logits.data[dead] = -8.0                               # opacity 3e-4 < min_opacity
    s = MCMCStrategy(cap_max=33, start=0, every=1, min_opacity=0.005, grow_rate=0.5, noise_lr=0.0)
    s.initialize(m, opt, 1.0)
    live_means = m.means.detach()[torch.sigmoid(m.opacity_logits) > 0.005].clone()
    g = torch.Generator().manual_seed(0)
    n_moved = s.relocate(m, opt, g)
    assert n_moved == 4 and float(torch.sigmoid(m.opacity_logits.detach()).min()) > 0.005
    for i in dead.tolist():                                          # each moved onto a live splat
        assert bool(((live_means - m.means[i].detach()).norm(dim=-1) < 1e-7).any())
        assert torch.all(opt.state[m.means]["exp_avg"][i] == 0)
    for step in range(5):                                            # grow: +50% per round, capped at 33
        s.step_post_backward(m, opt, step, {}, g)
        assert m.num <= 33
    assert m.num == 33


def test_mcmc_noise_moves_transparent_splats_only_and_regulariser():
    m, opt = _model_and_adam(n=10)
    m.opacity_logits.data[:5] = 6.0                                  # opaque: gate ~ sigmoid(-99) ~ 0
    m.opacity_logits.data[5:] = -8.0                                 # transparent: gate ~ 0.5
    before = m.means.detach().clone()
    s = MCMCStrategy(start=10 ** 6, noise_lr=1e3)
    s.initialize(m, opt, 1.0)
    s.step_post_backward(m, opt, 0, {}, torch.Generator().manual_seed(0))
    moved = (m.means.detach() - before).norm(dim=-1)
    assert float(moved[:5].max()) < 1e-12 and float(moved[5:].min()) > 0
    reg = s.regularization(m)
    expected = 0.01 * torch.sigmoid(m.opacity_logits).mean() + 0.01 * torch.exp(m.log_scales).mean()
    torch.testing.assert_close(reg, expected)
    reg.backward()
    assert m.opacity_logits.grad is not None and torch.isfinite(m.log_scales.grad).all()


def test_course_keeps_the_set_fixed():
    m, opt = _model_and_adam(isotropic=True)
    s = STRATEGIES.build({"name": "course"})
    s.initialize(m, opt, 1.0)
    before = {k: getattr(m, k).detach().clone() for k in PARAM_NAMES}
    for step in range(300):
        assert s.step_post_backward(m, opt, step, _info(torch.ones(20), 20)) == {}
    assert s.regularization(m) is None
    for k in PARAM_NAMES:
        assert torch.equal(getattr(m, k), before[k]), k
    assert m.log_scales.shape == (20, 1) and m.log_scales3.shape == (20, 3)


def _default_events(until, every, reset_every, steps, extra_info):
    """(event, steps done) of a DefaultStrategy (start = every, every splat above the gradient
    threshold, opacities put back after each step) over ``steps`` steps; ``extra_info(step)``
    adds to each step's info (its schedule or until scale)."""
    m, opt = _model_and_adam()
    s = DefaultStrategy(start=every, until=until, every=every, grad_threshold=10.0, opacity_reset_every=reset_every,
                        reset_value=0.01, max_world_scale=0.0)
    s.initialize(m, opt, scene_extent=1.0)
    m.opacity_logits.data[:] = 3.0
    seen = []
    for step in range(steps):
        if s.step_post_backward(m, opt, step, {**_info(torch.ones(20), 20), **extra_info(step)}):
            seen.append(("densify", step + 1))
        if float(m.opacity_logits.detach().max()) < 0:
            seen.append(("reset", step + 1))
        m.opacity_logits.data[:] = 3.0
    return seen


def test_default_events_follow_a_compressed_schedule():
    """info["schedule"] two nominal steps per step: densify (every 4 from 4, until 8) at steps 2
    and 4, the opacity reset (every 6) at step 3, nothing after step 4 (nominal 8 = until)."""
    seen = _default_events(8, 4, 6, 6, lambda step: {"schedule": (2.0 * step, 2.0 * step + 2.0)})
    assert seen == [("densify", 2), ("reset", 3), ("densify", 4)]


def test_mcmc_events_follow_a_compressed_schedule():
    """Grow (every 2 in (start 1, until 9)) at nominal 2, 4, 6, 8: steps 1, 2, 3, 4 of a schedule
    covering two nominal steps per step; by step, at steps 2, 4, 6, 8 (0-based 1, 3, 5, 7)."""
    def grown_at(per_step):
        m, opt = _model_and_adam(n=10)
        s = MCMCStrategy(cap_max=10 ** 6, start=1, until=9, every=2, grow_rate=0.1, noise_lr=0.0)
        s.initialize(m, opt, 1.0)
        at = []
        for step in range(8):
            info = {"schedule": (per_step * step, per_step * (step + 1))} if per_step != 1 else {}
            if s.step_post_backward(m, opt, step, info, torch.Generator().manual_seed(0)):
                at.append(step)
        return at
    assert grown_at(1) == [1, 3, 5, 7] and grown_at(2) == [0, 1, 2, 3]
