"""Under a time budget the turntables take what is left after the test views: counts by hand, and the
probe frame that prices them against a fake clock (the budget's own)."""

import pytest
import torch

from l3d_app.render import previews
from l3d_app.render.previews import reuse_probe_frames, write_turntables
from l3d_app.runtime.budget import TimeBudget, frames_that_fit, views_in_validations


def test_all_frames_without_a_budget():
    assert frames_that_fit(36, None, 1.0) == 36
    assert frames_that_fit(0, 5.0, 0.1) == 0


@pytest.mark.parametrize("left,expected", [(100.0, 36), (10.0, 36), (5.0, 24), (2.0, 9), (1.5, 0), (-3.0, 0)])
def test_frames_that_fit_the_time_left(left, expected):
    """0.2048 s per frame (of all gifs); fewer than 8: none."""
    assert frames_that_fit(36, left, 0.2048) == expected


def test_a_short_turntable_is_kept_whole_when_it_fits():
    assert frames_that_fit(4, 1.0, 0.2048) == 4      # 4 asked, 4 fit (0.82 s)
    assert frames_that_fit(4, 0.5, 0.2048) == 0      # 2 fit: fewer than asked and than 8


class _Orbit:
    """A fake orbit of ``n`` cameras: ``len`` and slicing as :class:`Cameras` have."""

    def __init__(self, n):
        self.n = n

    def __len__(self):
        return self.n

    def __getitem__(self, index):
        return _Orbit(len(range(self.n)[index]) if isinstance(index, slice) else 1)


def _run(monkeypatch, tmp_path, elapsed, budget=590.0, asked=36, encode=0.0):
    """Two gifs whose frames cost 0.125 s each to render and ``encode`` s each to GIF-encode on a fake
    clock that reads ``elapsed`` at the start: one probe frame of both = 0.25 s + 2 x ``encode``."""
    clock = {"t": float(elapsed)}
    written, notes = [], []
    monkeypatch.setattr(previews, "write_turntable", lambda path, fn, cams, fps: written.append((path.name, cams.n)))
    real_gif_bytes = previews.gif_bytes

    def timed_gif_bytes(frames, fps):
        clock["t"] += encode * len(frames)
        return real_gif_bytes(frames, fps)
    monkeypatch.setattr(previews, "gif_bytes", timed_gif_bytes)

    def frames_fn(cams):
        clock["t"] += 0.125 * cams.n
        return torch.full((cams.n, 4, 4, 3), 0.5)

    timer = TimeBudget(budget, clock=lambda: clock["t"], note=lambda tag, text: notes.append((tag, text)))
    frames = write_turntables({tmp_path / "render.gif": frames_fn, tmp_path / "geometry.gif": frames_fn}, _Orbit,
                              asked, 12.0, timer)
    return frames, written, notes


def test_the_probe_frames_price_the_turntables(monkeypatch, tmp_path):
    """36 asked: 4 probe frames (0.25 s each for both gifs, 1 s), reused; 5 s left before them, 4 s
    after: 4 + 16 = 20."""
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=585.0)
    assert frames == 20 and written == [("render.gif", 20), ("geometry.gif", 20)]
    assert notes and notes[0][0] == "gifs" and "20 of 36" in notes[0][1] and "0.25 s per frame" in notes[0][1]
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=100.0)          # plenty: all, no note
    assert frames == 36 and written == [("render.gif", 36), ("geometry.gif", 36)] and not notes
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=587.75)         # 2.25 s: 4 + 4 = 8, kept
    assert frames == 8 and "8 of 36" in notes[0][1]
    # 1 s: after probe frame 0 (0.25 s) the other 7 of the least gif (1.75 s) do not fit: no further
    # probe frame is rendered (the held-out nerf_baseline 60 s run spent 9.9 s on 4 probe frames with 1.2 s left)
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=589.0)
    assert frames == 0 and written == [] and "probe frame 0" in notes[0][1] and "no gif" in notes[0][1]
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=589.5)          # 0.5 s: none either
    assert frames == 0 and written == [] and "no gif" in notes[0][1]
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=10_000.0, budget=0)   # no budget: no probe
    assert frames == 36 and written == [("render.gif", 36), ("geometry.gif", 36)] and not notes
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=585.0, asked=10)   # gcd(10, 4) = 2 probes
    assert frames == 10 and not notes


def test_the_probe_prices_the_gif_encoding_too(monkeypatch, tmp_path):
    """0.125 s to render + 0.025 s to encode a frame of each of two gifs: 0.3 s a frame; 5.1 s left,
    less the probe (1 s rendering, 0.2 s encoding) and its 0.2 s of encoding again in the gifs: 3.7 s,
    4 + 12 = 16 (the rendering alone would say 4 + 14 -> 16 + 2, and the gifs would run past the budget)."""
    frames, written, notes = _run(monkeypatch, tmp_path, elapsed=584.9, encode=0.025)
    assert frames == 16 and written == [("render.gif", 16), ("geometry.gif", 16)]
    assert "16 of 36" in notes[0][1] and "0.30 s per frame" in notes[0][1]


@pytest.mark.parametrize("n,p", [(36, 4), (8, 4), (4, 4), (10, 2), (9, 1)])
def test_the_probe_frames_are_reused_where_the_orbit_holds_them(n, p):
    """An orbit of n frames with p probe frames rendered first: the same frames as rendering all n
    (each frame a function of its camera), and only n - p of them rendered again."""
    from l3d_app.render.turntable import orbit_cameras
    calls = []

    def frames_fn(cams):
        calls.append(len(cams))
        return torch.cat([cams.R.reshape(-1, 9), cams.t], 1)[:, None, None, :].expand(-1, 2, 3, -1).clone()

    orbit = lambda k: orbit_cameras(k, 4.0, 30.0, 40.0, 8, up=[0.0, 0.0, 1.0])  # noqa: E731
    probed = frames_fn(orbit(p))
    calls.clear()
    got = reuse_probe_frames(frames_fn, probed)(orbit(n))
    assert torch.equal(got, frames_fn(orbit(n)))
    assert calls[0] == n - p or (n == p and len(calls) == 1)


def test_an_orbit_without_the_probe_azimuths_is_refused():
    from l3d_app.render.turntable import orbit_cameras
    fn = reuse_probe_frames(lambda c: torch.zeros(len(c), 1, 1, 3), torch.zeros(4, 1, 1, 3))
    with pytest.raises(ValueError, match="does not hold 4"):
        fn(orbit_cameras(10, 4.0, 30.0, 40.0, 8))


def test_the_loop_reserve_holds_the_test_views_only():
    """4 val views at one ray, 20 test views at 2 x 2 rays: 20 x 4 / 4 = 20 validations (no gif frames)."""
    assert views_in_validations(4, 20, 2, 1) == pytest.approx(20.0)
