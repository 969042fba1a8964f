"""Turntable frame width: an explicit ``turntable_size`` wins; 0 means the data's width,
capped by a task's ``turntable_max`` (volsdf: 128 px, so a 256 px scene's gifs cost a
quarter of the pixels)."""
from l3d_app.tasks.field_common import turntable_width


def test_zero_size_takes_the_data_width_under_the_cap(compose):
    cfg = compose("task=volsdf")
    assert int(cfg.turntable_size) == 0 and int(cfg.turntable_max) == 128
    assert turntable_width(cfg, 256) == 128     # 256 px data: capped
    assert turntable_width(cfg, 64) == 64       # smaller data: its own width, never upsampled


def test_an_explicit_size_overrides_the_cap(compose):
    cfg = compose("task=volsdf", "turntable_size=300")
    assert turntable_width(cfg, 256) == 300


def test_a_task_without_a_cap_keeps_the_data_width(compose):
    cfg = compose("task=train_nerf")
    assert "turntable_max" not in cfg
    assert turntable_width(cfg, 800) == 800


def test_a_zero_cap_means_no_cap(compose):
    cfg = compose("task=volsdf", "turntable_max=0")
    assert turntable_width(cfg, 800) == 800
