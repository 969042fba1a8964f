"""Under a time budget the turntables take what is left after the test views: counts by hand, and the
probe frame that prices them against a fake clock."""

import time
from types import SimpleNamespace

import pytest
import torch
from omegaconf import OmegaConf

from l3d_app.tasks import field_common
from l3d_app.tasks.field_common import evals_after_training, turntable_frames_that_fit, write_turntables


def test_all_frames_without_a_budget():
    assert turntable_frames_that_fit(36, None, 1.0) == 36
    assert turntable_frames_that_fit(0, 5.0, 0.1) == 0


@pytest.mark.parametrize("left,expected", [(100.0, 36), (10.0, 36), (5.0, 24), (2.0, 9), (1.5, 0), (-3.0, 0)])
def test_frames_that_fit_the_time_left(left, expected):
    """0.2048 s per frame (of all gifs); fewer than 8: none."""
    assert turntable_frames_that_fit(36, left, 0.2048) == expected


def test_a_short_turntable_is_kept_whole_when_it_fits():
    assert turntable_frames_that_fit(4, 1.0, 0.2048) == 4      # 4 asked, 4 fit (0.82 s)
    assert turntable_frames_that_fit(4, 0.5, 0.2048) == 0      # 2 fit: fewer than asked and than 8


class _Log:
    def __init__(self):
        self.notes = []

    def text(self, tag, value):
        self.notes.append((tag, value))


def _run(monkeypatch, tmp_path, elapsed, budget=590.0, asked=36, encode=0.0):
    """Two gifs whose frames cost 0.125 s each to render and ``encode`` s each to GIF-encode on a fake
    clock: one probe frame of both = 0.25 s + 2 x ``encode``."""
    clock = {"t": 0.0}
    monkeypatch.setattr(time, "perf_counter", lambda: clock["t"])
    monkeypatch.setattr(field_common, "turntable_orbit", lambda cfg, data, n, device: SimpleNamespace(n=n))
    written = []
    import l3d_app.render.turntable as turntable
    import l3d_app.runtime.media as media
    monkeypatch.setattr(turntable, "write_turntable", lambda path, fn, cams, fps: written.append((path.name, cams.n)))
    real_gif_bytes = media.gif_bytes

    def timed_gif_bytes(frames, fps):
        clock["t"] += encode * len(frames)
        return real_gif_bytes(frames, fps)
    monkeypatch.setattr(media, "gif_bytes", timed_gif_bytes)

    def frames_fn(cams):
        clock["t"] += 0.125 * cams.n
        return torch.full((cams.n, 4, 4, 3), 0.5)

    ctx = SimpleNamespace(stopwatch=SimpleNamespace(elapsed=elapsed), logger=_Log(), device="cpu",
                          path=lambda name: tmp_path / name)
    cfg = OmegaConf.create({"gif_frames": asked, "time_budget": budget, "fps": 12})
    frames = write_turntables(cfg, ctx, None, {"render.gif": frames_fn, "geometry.gif": frames_fn})
    return frames, written, ctx.logger.notes


def test_the_probe_frame_prices_the_turntables(monkeypatch, tmp_path):
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=585.0)          # 5 s left at 0.25 s: 20
    assert frames == 20 and written == [("render.gif", 20), ("geometry.gif", 20)]
    assert notes and notes[0][0] == "gifs" and "20 of 36" in notes[0][1] and "0.25 s per frame" in notes[0][1]
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=100.0)          # plenty: all, no note
    assert frames == 36 and written == [("render.gif", 36), ("geometry.gif", 36)] and not notes
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=589.0)          # 1 s: 4 frames < 8: none
    assert frames == 0 and written == [] and "no gif" in notes[0][1]
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=10_000.0, budget=0)   # no budget: no probe
    assert frames == 36 and written == [("render.gif", 36), ("geometry.gif", 36)] and not notes


def test_the_probe_prices_the_gif_encoding_too(monkeypatch, tmp_path):
    """0.125 s to render + 0.025 s to encode a frame of each of two gifs: 0.3 s a frame; 5 s left: 16
    frames (the rendering alone would say 20, and the gifs would run 1 s past the budget)."""
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=585.0, encode=0.025)
    assert frames == 16 and written == [("render.gif", 16), ("geometry.gif", 16)]
    assert "16 of 36" in notes[0][1] and "0.30 s per frame" in notes[0][1]


def test_the_loop_reserve_holds_the_test_views_only():
    """4 val views at one ray, 20 test views at 2 x 2 rays: 20 x 4 / 4 = 20 validations (no gif frames)."""
    assert evals_after_training(4, 20, 2, 1) == pytest.approx(20.0)
