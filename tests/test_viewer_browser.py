"""The live viewer in a real browser: gs_train with viewer=true, its page opened in headless Chromium.

Skipped, with the reason, where no Chromium is installed (.ci/run installs Debian's ``chromium``).
From screenshots: the page draws the scene (not just the page's background), moving the camera
changes the picture (far more than the same wait without a move), and a page opened later in
the run shows a later step's model than the first page did; training goes on while pages look.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (apt-get install chromium)")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run", "--disable-quic", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
SHOWN = re.compile(r"model shown: step (\d+)")
TRAINED = re.compile(r"step: (\d+)")


def _wait_for(fn, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        out = fn()
        if out:
            return out
        time.sleep(0.25)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _shot(page) -> np.ndarray:
    """The page's 3D view as (H, W, 3) float in [0, 1], the GUI panel's column and the corners cut off."""
    from PIL import Image
    import io

    img = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), dtype=np.float64) / 255.0
    h, w = img.shape[:2]
    return img[int(0.3 * h):int(0.9 * h), int(0.05 * w):int(0.45 * w)]


def _coloured(img: np.ndarray) -> float:
    """Share of the pixels whose channels differ by more than 0.25 (not white, grey or black)."""
    return float(((img.max(-1) - img.min(-1)) > 0.25).mean())


def _step(page, pattern) -> int:
    m = pattern.search(page.inner_text("body"))
    return int(m.group(1)) if m else -1


@pytest.fixture(scope="module")
def training(tmp_path_factory):
    """gs_train on the built-in scene with viewer=true, running until the module's tests end."""
    run_dir = tmp_path_factory.mktemp("viewer_run")
    env = {**os.environ, "L3D_NO_PROGRESS": "1"}
    proc = subprocess.Popen([sys.executable, "main.py", "task=gs_train", "viewer=true", "+viewer_port=0", "+viewer_width=160",
                             "+viewer_period=0.5", "iters=1000000", "time_budget=0", "eval_every=50", "tensorboard=false",
                             "threads=1", "data.n_train=24", "data.n_val=2", "data.n_test=2", "n_init=1500",
                             f"data.cache_dir={run_dir / 'cache'}", f"hydra.run.dir={run_dir}"],
                            cwd=REPO, env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    url = None
    try:
        for line in proc.stderr:
            m = re.search(r"viewer: (http://\S+)", line)
            if m:
                url = m.group(1)
                break
        assert url, "gs_train did not print the viewer's address"
        yield url
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_the_page_draws_the_model_and_follows_the_camera_and_the_training(training):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            first = browser.new_page(viewport={"width": 640, "height": 480})
            first.goto(training)
            step_a = _wait_for(lambda: _step(first, SHOWN) > 0 and _step(first, SHOWN), 240, "the first page's model")
            # the scene is drawn: the built-in scene's coloured objects on its white background fill part of the view
            # (the empty page is white with thin blue frustum lines)
            _wait_for(lambda: _coloured(_shot(first)) > 0.05, 60, "the first page's picture")
            time.sleep(1.0)
            a = _shot(first)
            assert _coloured(a) > 0.05, f"only {_coloured(a):.3f} of the view is coloured: the model is not drawn"

            still = np.abs(_shot(first) - a).mean()            # the same camera a moment later (training goes on)
            box = first.viewport_size
            first.mouse.move(box["width"] * 0.25, box["height"] * 0.6)
            first.mouse.down()
            first.mouse.move(box["width"] * 0.25 + 200, box["height"] * 0.6 + 40, steps=10)
            first.mouse.up()
            moved = _wait_for(lambda: (d := np.abs(_shot(first) - a).mean()) > 3 * still + 0.02 and d, 60,
                              "the picture to follow the camera")
            assert moved > 3 * still + 0.02

            trained_a = _step(first, TRAINED)
            second = browser.new_page(viewport={"width": 640, "height": 480})
            second.goto(training)
            step_b = _wait_for(lambda: _step(second, SHOWN) > step_a and _step(second, SHOWN), 240,
                               "the second page's model")
            assert step_b > step_a                              # opened later: a later model
            _wait_for(lambda: _coloured(_shot(second)) > 0.05, 60, "the second page's picture")
            _wait_for(lambda: _step(first, TRAINED) > trained_a, 120, "training to go on while pages look")
        finally:
            browser.close()
