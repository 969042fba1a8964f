"""bench/free_space_end_rules.py's helper against a hand-built reference: the plain-pixel measure
against a naive window loop (the multi-view cut it also reports is the library's:
tests/test_free_space_multi_view_cut.py)."""

import torch

from bench_scripts import load_bench_script


def _rules():
    return load_bench_script("free_space_end_rules")


def test_plain_texture_matches_a_naive_window_loop():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 7, 9, 3, generator=g, dtype=torch.float64)
    got = _rules().plain_texture(img, 5)
    want = torch.empty(2, 7, 9, dtype=torch.float64)
    for v in range(2):
        for y in range(7):
            for x in range(9):
                win = img[v, max(0, y - 2):y + 3, max(0, x - 2):x + 3].reshape(-1, 3)   # inside the image only
                want[v, y, x] = win.std(0, unbiased=False).mean()
    torch.testing.assert_close(got, want)
    assert float(_rules().plain_texture(torch.full((1, 6, 6, 3), 0.4), 5).abs().max()) < 1e-6
