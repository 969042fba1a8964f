"""The built-in scans (data=shape_scans): the visibility test against a naive z-buffer, partial and noisy
clouds, 12 classes whose confusable pairs differ in one part, part labels, the cache."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from l3d_app.data.shape_scans import (ARMS, BACK, CLASS_NAMES, GENERATORS, HANDLE, PART_NAMES, scan_object,
                                      shape_scans)
from l3d_app.errors import UserError
from l3d_app.geometry.partial_scan import image_plane_basis, view_direction, visible_points


def test_visibility_matches_a_naive_z_buffer():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(600, 3, generator=g, dtype=torch.float64) * 1.6 - 0.8
    d = view_direction(40.0, 25.0).double()
    got = visible_points(pts, d, grid=8, extent=1.0, tolerance=0.1)
    u, v = image_plane_basis(d)
    nearest = {}
    cells = []
    for p in pts:                                          # a dictionary z-buffer, one point at a time
        a, b = float(p @ u), float(p @ v)
        cell = (min(max(int(math.floor((a + 1) / 2 * 8)), 0), 7), min(max(int(math.floor((b + 1) / 2 * 8)), 0), 7))
        cells.append(cell)
        nearest[cell] = min(nearest.get(cell, math.inf), float(p @ d))
    expect = [float(p @ d) <= nearest[c] + 0.1 for p, c in zip(pts, cells)]
    assert got.tolist() == expect
    assert torch.allclose(d, -torch.tensor([math.cos(math.radians(25)) * math.sin(math.radians(40)),
                                            math.sin(math.radians(25)),
                                            math.cos(math.radians(25)) * math.cos(math.radians(40))],
                                           dtype=torch.float64))


def test_a_scan_sees_the_front_and_its_noise_is_what_was_asked():
    rng = lambda: np.random.default_rng([0, CLASS_NAMES.index("bottle"), 3])     # noqa: E731
    clean, lab, share = scan_object(GENERATORS["bottle"](rng()), 1024, torch.Generator().manual_seed(5), 0.0, 0.0,
                                    noise=0.0)
    noisy, lab2, _ = scan_object(GENERATORS["bottle"](rng()), 1024, torch.Generator().manual_seed(5), 0.0, 0.0,
                                 noise=0.02)
    assert torch.equal(lab, lab2) and 0.1 < share < 0.6                 # a closed bottle: about its front half
    assert float((noisy - clean).std()) == pytest.approx(0.02, rel=0.06)
    # the scanner at azimuth 0 looks along -z: it keeps the +z half of the round bottle, half as deep as wide
    extent = clean.amax(0) - clean.amin(0)
    assert float(extent[2] / extent[0]) < 0.7 and float(clean.norm(dim=-1).max()) == pytest.approx(1.0, abs=1e-5)


def test_confusable_classes_differ_in_one_part():
    def parts_of(name, i):
        rng = np.random.default_rng([0, CLASS_NAMES.index(name), i])
        return {label for _, label in GENERATORS[name](rng)}

    for i in range(6):
        assert parts_of("armchair", i) == parts_of("chair", i) | {ARMS} and ARMS not in parts_of("chair", i)
        assert BACK in parts_of("chair", i) and BACK not in parts_of("stool", i)
        assert parts_of("mug", i) == parts_of("cup", i) | {HANDLE}
        assert parts_of("desk_lamp", i) == parts_of("lamp", i)          # same parts, a bent stem
    seen = []                                                            # a mug's handle is hidden in some scans
    for i in range(8):
        rng = np.random.default_rng([0, CLASS_NAMES.index("mug"), i])
        _, lab, _ = scan_object(GENERATORS["mug"](rng), 512, torch.Generator().manual_seed(i), rng.uniform(0, 360),
                                rng.uniform(-10, 50))
        seen.append(int((lab == HANDLE).sum()))
    assert min(seen) < 5 and max(seen) > 25, seen


def test_shape_scans_dataset_splits_labels_and_cache(tmp_path):
    data = shape_scans(train_per_class=3, test_per_class=2, num_points=128, cache_dir=str(tmp_path), val_fraction=0.0)
    assert len(CLASS_NAMES) >= 10 and data.class_names == list(CLASS_NAMES) and data.part_names == list(PART_NAMES)
    assert data.train.points.shape == (36, 128, 3) and data.test.points.shape == (24, 128, 3)
    assert data.train.labels.tolist() == [c for c in range(12) for _ in range(3)]
    assert float(data.train.points.norm(dim=-1).max()) < 1.1               # unit ball plus noise
    allowed = {"chair": {0, 1, 2}, "table": {2, 4}, "bottle": {5, 6}, "cup": {5}, "lamp": {9, 10, 11}}
    for name, parts in allowed.items():
        got = set(data.train.parts[data.train.labels == CLASS_NAMES.index(name)].unique().tolist())
        assert got <= parts, (name, got)
    again = shape_scans(train_per_class=3, test_per_class=2, num_points=128, cache_dir=str(tmp_path), val_fraction=0.0)
    assert torch.equal(again.test.points, data.test.points) and len(list(tmp_path.glob("shape_scans_*.npz"))) == 1
    with pytest.raises(UserError, match="unknown shape_scans class"):
        shape_scans(classes=["sofa"], cache_dir=str(tmp_path))
    with pytest.raises(UserError, match="elevation"):
        shape_scans(elevation=[50, 10], cache_dir=str(tmp_path))
