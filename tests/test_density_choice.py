"""density=auto (render/sdf/density_choice.py): the cameras-below fraction against a naive count, the choice at
and around the threshold, the data's up axis, and NeuS's width derived from VolSDF's knobs."""

import math
from types import SimpleNamespace

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.render.sdf.density_choice import BELOW_FRACTION, below_fraction, choose_density, possible_configs


def _data(elevations_deg, up=None, box=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))):
    """Cameras 4 units from the origin at the given elevations (look_at: +Y up), every one a training view."""
    n = len(elevations_deg)
    cams = look_at_cameras(torch.full((n,), 4.0), torch.tensor(elevations_deg, dtype=torch.float32),
                           torch.linspace(0.0, 300.0, n), 40.0, 16)
    return SimpleNamespace(cameras=cams, train=torch.arange(n), scene_box=torch.tensor(box), up=up)


def test_below_fraction_matches_a_naive_count():
    g = torch.Generator().manual_seed(0)
    centres, centre = torch.randn(200, 3, generator=g, dtype=torch.float64), torch.tensor([0.1, -0.2, 0.3]).double()
    up = torch.tensor([0.3, 2.0, -0.5]).double()
    unit = [float(u) / math.sqrt(sum(float(v) ** 2 for v in up)) for u in up]
    naive = sum(1 for c in centres.tolist() if sum((c[i] - float(centre[i])) * unit[i] for i in range(3)) < 0) / 200
    assert below_fraction(centres, up, centre) == pytest.approx(naive, abs=1e-12)
    assert below_fraction(centres[:0], up, centre) == 0.0


def test_auto_picks_neus_from_a_quarter_below_and_volsdf_under_it(compose):
    cfg = compose("task=volsdf").density
    assert cfg.name == "auto" and "below_fraction" not in cfg and BELOW_FRACTION == 0.25
    above = _data([10.0, 30.0, 50.0, 70.0] * 2, up=[0.0, 1.0, 0.0])
    quarter = _data([-20.0, 30.0, 50.0, 70.0] * 2, up=[0.0, 1.0, 0.0])
    under = _data([-20.0] + [30.0] * 4, up=[0.0, 1.0, 0.0])            # 1 of 5: 20 %
    for data, name, fraction in ((above, "volsdf", 0.0), (quarter, "neus", 0.25), (under, "volsdf", 0.2)):
        chosen, below = choose_density(cfg, data)
        assert (chosen["name"], below) == (name, pytest.approx(fraction)), (name, below)


def test_the_choice_reads_the_datas_up_axis_and_the_boxs_centre(compose):
    cfg = compose("task=volsdf").density
    ring = _data([20.0] * 8, up=[0.0, 1.0, 0.0])    # 20 degrees above the XZ plane: none below with +Y up ...
    chosen, below = choose_density(cfg, ring)
    assert (chosen["name"], below) == ("volsdf", 0.0)
    ring.up = [0.0, 0.0, 1.0]                        # ... 4 of the 8 at z < 0 with +Z up: NeuS
    chosen, below = choose_density(cfg, ring)
    assert (chosen["name"], below) == ("neus", pytest.approx(0.5))
    # cameras 20 degrees up about the origin (y = 1.37) lie below a box centred at y = 2.5: all below, NeuS
    chosen, below = choose_density(cfg, _data([20.0] * 6, up=[0.0, 1.0, 0.0], box=((-1, 1.5, -1), (1, 3.5, 1))))
    assert (chosen["name"], below) == ("neus", 1.0)


def test_neus_under_auto_takes_its_width_and_schedule_from_volsdfs_knobs(compose):
    volsdf, neus = possible_configs(compose("task=volsdf", "beta=0.25", "density.beta_end=0.004").density)
    assert [volsdf[k] for k in ("name", "beta", "beta_end", "mode")] == ["volsdf", 0.25, 0.004, "anneal"]
    assert [neus[k] for k in ("name", "mode", "anneal_fraction")] == ["neus", "anneal", 0.8]
    assert neus["s"] == pytest.approx(4.0) and neus["s_end"] == pytest.approx(250.0)
    fixed = compose("task=volsdf", "density=volsdf")
    assert possible_configs(fixed.density) == (fixed.density,)            # an explicit density is kept as is
    assert choose_density(fixed.density, _data([-40.0] * 4, up=[0, 1, 0]))[0]["name"] == "volsdf"


@pytest.mark.parametrize("fraction", [0, -0.1, 1.5, "half", True])
def test_a_below_fraction_outside_0_1_is_refused(compose, fraction):
    cfg = {**compose("task=volsdf").density, "below_fraction": fraction}
    with pytest.raises(UserError, match="density.below_fraction must lie in"):
        possible_configs(cfg)
