"""Procedural prompt images and the independent prompt checker."""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.data.prompt_images import (ANY, BACKGROUND_NAMES, COLOUR_NAMES, SHAPES, parse_prompt,
                                        prompt_batch, prompt_text, render_prompt_images, sample_labels,
                                        shape_masks)
from l3d_app.errors import UserError
from l3d_app.metrics.prompt_match import check_image, largest_component, match_rate


def test_parse_prompt_slots_aliases_and_errors():
    assert parse_prompt("a red circle on white") == (0, 0, 0)
    assert parse_prompt("A Blue Square") == (COLOUR_NAMES.index("blue"), 1, ANY)
    assert parse_prompt("a triangle on a grey background") == (ANY, 2, BACKGROUND_NAMES.index("gray"))
    assert parse_prompt("a purple disc") == (COLOUR_NAMES.index("magenta"), 0, ANY)
    assert parse_prompt("") == (ANY, ANY, ANY)
    for bad in ("a red dragon", "a red blue circle", "a circle square"):
        with pytest.raises(UserError):
            parse_prompt(bad)
    for c in range(len(COLOUR_NAMES)):
        for s in range(len(SHAPES)):
            for b in (ANY, 0, 1, 2):
                assert parse_prompt(prompt_text(c, s, b)) == (c, s, b)


@pytest.mark.parametrize("shape,area", [(0, math.pi), (1, 4.0), (2, 2.0)])
def test_shape_areas_match_analytic(shape, area):
    """Soft coverage sums to the analytic area (r^2 units): pi r^2, (2r)^2, base*height/2 = 2r^2."""
    r = 10.0
    m = shape_masks(torch.tensor([shape]), torch.tensor([[32.0, 32.0]]), torch.tensor([r]), 64)
    assert abs(float(m.sum()) / (r * r) - area) / area < 0.02


def test_images_are_valid_and_reproducible():
    a, la = prompt_batch(16, 32, torch.Generator().manual_seed(3))
    b, lb = prompt_batch(16, 32, torch.Generator().manual_seed(3))
    assert a.shape == (16, 3, 32, 32) and float(a.min()) >= 0 and float(a.max()) <= 1
    assert torch.equal(a, b) and torch.equal(la, lb)


def test_default_jitter_is_small_and_within_its_ranges():
    """Defaults: radius 22-30% of the side, centre within 5% of the side of the middle."""
    g = torch.Generator().manual_seed(5)
    labels = torch.tensor([[0, 1, 0]] * 200)  # red squares on white: the shape's box is exact
    images = render_prompt_images(labels, 64, g, jitter=0.0)
    inside = (images[:, 1] < 0.5)  # red channel high, green low inside the square
    for m in inside:
        ys, xs = torch.nonzero(m, as_tuple=True)
        side = float(xs.max() - xs.min() + 1)
        assert 0.44 * 64 - 2 <= side <= 0.60 * 64 + 2
        cx, cy = float(xs.float().mean()) + 0.5, float(ys.float().mean()) + 0.5
        assert abs(cx - 32) <= 0.05 * 64 + 1 and abs(cy - 32) <= 0.05 * 64 + 1


def test_checker_accepts_clean_samples():
    # the checker is tested on a wider position/size jitter than the prior's default
    g = torch.Generator().manual_seed(0)
    labels = sample_labels(240, g)
    images = render_prompt_images(labels, 32, g, min_radius=0.2, max_radius=0.32, max_offset=0.12)
    prompts = [prompt_text(*l.tolist()) for l in labels]
    assert match_rate(images, prompts) == 1.0
    # partial prompts (unnamed slots) match too
    partial = [prompt_text(l[0].item(), l[1].item(), ANY) for l in labels[:30]]
    assert match_rate(images[:30], partial) == 1.0


def test_checker_rejects_wrong_prompts_and_non_images():
    g = torch.Generator().manual_seed(1)
    labels = torch.tensor([[0, 0, 0], [2, 1, 1], [3, 2, 2]] * 10)
    images = render_prompt_images(labels, 32, g)
    for img, (c, s, b) in zip(images, labels.tolist()):
        assert not check_image(img, prompt_text((c + 1) % 6, s, b)).match
        assert not check_image(img, prompt_text(c, (s + 1) % 3, b)).match
        assert not check_image(img, prompt_text(c, s, (b + 1) % 3)).match
    grey = torch.full((32, 32, 3), 0.5)
    assert not check_image(grey, "a red circle").match
    noise = torch.rand(32, 32, 3, generator=g)
    assert not check_image(noise, "a red circle").match
    two = render_prompt_images(torch.tensor([[0, 1, 0]]), 32, g)[0].clone()
    two[:, :6, :6] = torch.tensor([0.1, 0.2, 0.9]).view(3, 1, 1)  # a second, blue blob
    v = check_image(two, "a red square on white")
    assert v.purity < 1.0


def test_largest_component_known_mask():
    m = torch.zeros(8, 8, dtype=torch.bool)
    m[0:2, 0:2] = True          # 4 pixels
    m[4:8, 3:6] = True          # 12 pixels
    m[2, 7] = True              # 1 pixel (diagonal neighbours do not connect)
    comp = largest_component(m)
    assert int(comp.sum()) == 12 and bool(comp[4:8, 3:6].all())
    assert not bool(largest_component(torch.zeros(4, 4, dtype=torch.bool)).any())
