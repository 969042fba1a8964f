"""The built-in scans (data=shape_scans): the visibility test against a naive z-buffer, partial and noisy
clouds, 12 classes whose confusable pairs differ in one part, part labels, the cache."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from l3d_app.data.scanner import occluded, scan_object
from l3d_app.data.shape_scans import (ARMS, BACK, BACKGROUND, CLASS_NAMES, GENERATORS, HANDLE, NECK, PART_NAMES,
                                      shape_scans, surroundings)
from l3d_app.geometry import primitives as prim
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


def test_an_occluder_hides_a_disc_of_the_view_and_leaves_at_least_40_percent():
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(3000, 3, generator=g, dtype=torch.float64) * 1.6 - 0.8
    seen = torch.rand(3000, generator=g) < 0.7
    d = view_direction(70.0, 30.0).double()
    for trial, radius in enumerate([(0.3, 0.3), (0.1, 0.5), (5.0, 5.0)]):
        hidden = occluded(pts, seen, d, torch.Generator().manual_seed(trial), radius)
        assert not bool((hidden & ~seen).any()) and int(hidden.sum()) > 0
        # distance across the view, from the component along d (independent of the image-plane basis)
        offset = pts[:, None, :] - pts[None, hidden.nonzero()[:, 0], :]         # every point against every hidden one
        across = (offset.pow(2).sum(-1) - (offset @ d).pow(2)).clamp_min(0).sqrt()
        # the hidden set is a disc: some hidden sample (the centre) has every hidden sample within r of it and
        # every seen sample within r hidden, where r is the largest of those distances
        ok = False
        for j in range(across.shape[1]):
            r = float(across[hidden, j].max())
            inside = across[:, j] < r - 1e-9
            if bool((seen & inside & ~hidden).sum() == 0) and bool((~(seen & (across[:, j] <= r + 1e-9)) & hidden).sum() == 0):
                ok = True
                break
        assert ok, trial
        kept = float((seen & ~hidden).sum()) / float(seen.sum())
        assert kept >= 0.4 - 1e-3, (trial, kept)
        if radius == (0.3, 0.3):
            assert r == pytest.approx(0.3, abs=0.02) and kept > 0.5
        if radius == (5.0, 5.0):                                         # too large: capped at 60% hidden
            assert kept == pytest.approx(0.4, abs=2e-3)
    # an occlusion probability of 0 draws nothing: the scan is the one made without the knob
    rng = lambda: np.random.default_rng([0, CLASS_NAMES.index("mug"), 2])      # noqa: E731
    a = scan_object(GENERATORS["mug"](rng()), 256, torch.Generator().manual_seed(3), 30.0, 20.0)
    b = scan_object(GENERATORS["mug"](rng()), 256, torch.Generator().manual_seed(3), 30.0, 20.0, occlusion=0.0)
    c = scan_object(GENERATORS["mug"](rng()), 256, torch.Generator().manual_seed(3), 30.0, 20.0, occlusion=1.0)
    assert torch.equal(a[0], b[0]) and c[2] < a[2]


def _bottle():
    return GENERATORS["bottle"](np.random.default_rng([0, CLASS_NAMES.index("bottle"), 3]))


def test_clutter_is_background_cropped_to_the_object_and_can_hide_it():
    def scan(clutter=(), elevation=0.0):
        return scan_object(_bottle(), 1024, torch.Generator().manual_seed(5), 0.0, elevation, noise=0.0,
                           clutter=clutter)

    alone, lab_alone, share_alone = scan()
    _, lab_far, share_far = scan([(prim.box([10.0, 0.5, 0.0], [1.0, 1.0, 1.0]), BACKGROUND)])
    assert BACKGROUND not in lab_alone.tolist() and BACKGROUND not in lab_far.tolist()   # outside the crop
    assert share_far == pytest.approx(share_alone, abs=0.03)
    # a wall between the scanner (azimuth 0: on +z) and the bottle's lower half hides that half; the wall
    # itself stands outside the crop, so it leaves no points
    _, lab, share = scan([(prim.box([0.0, 0.35, 1.2], [2.0, 0.7, 0.05]), BACKGROUND)])
    assert share < 0.8 * share_alone and NECK in lab.tolist() and BACKGROUND not in lab.tolist()
    # the floor, 3 wide under a bottle about 0.6 wide: only its patch under the bottle (the crop) is kept
    pts, lab, _ = scan([(prim.box([0.0, -0.01, 0.0], [3.0, 0.02, 3.0]), BACKGROUND)], elevation=30.0)
    bg, obj = pts[lab == BACKGROUND], pts[lab != BACKGROUND]
    assert len(bg) > 20 and float(bg[:, 1].max()) <= float(obj[:, 1].min()) + 1e-3      # at the bottom
    reach = float(obj[:, 0].abs().max()) + 0.2 * float((obj.amax(0) - obj.amin(0)).max())
    assert float(bg[:, 0].abs().max()) <= reach


def test_surroundings_are_background_beside_the_object():
    shape = _bottle()
    mine = torch.cat([m.verts for m, _ in shape]).double()[:, [0, 2]]
    c1 = (mine.amin(0) + mine.amax(0)) / 2
    r1 = float((mine - c1).norm(dim=-1).max())
    for i in range(6):
        with_floor = i % 2 == 0
        around = surroundings(np.random.default_rng([7, i]), shape, floor=with_floor)
        assert {label for _, label in around} == {BACKGROUND}
        neighbour = torch.cat([m.verts for m, _ in (around[:-1] if with_floor else around)]).double()
        c2 = (neighbour[:, [0, 2]].amin(0) + neighbour[:, [0, 2]].amax(0)) / 2
        assert float((c2 - c1).norm()) > 0.8 * r1 and float(neighbour[:, 1].min()) >= -1e-6   # beside, on the floor
        if with_floor:
            top = around[-1][0].verts.double()
            assert float(top[:, 1].max()) == pytest.approx(0.0, abs=1e-9)
            assert float((top[:, [0, 2]] - c1).abs().max()) == pytest.approx(1.5 * r1, rel=1e-6)


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
    allowed = {"chair": {0, 1, 2, 12}, "table": {2, 4, 12}, "bottle": {5, 6, 12}, "cup": {5, 12}, "lamp": {9, 10, 11, 12}}
    for name, parts in allowed.items():
        got = set(data.train.parts[data.train.labels == CLASS_NAMES.index(name)].unique().tolist())
        assert got <= parts, (name, got)
    again = shape_scans(train_per_class=3, test_per_class=2, num_points=128, cache_dir=str(tmp_path), val_fraction=0.0)
    assert torch.equal(again.test.points, data.test.points) and len(list(tmp_path.glob("shape_scans_*.npz"))) == 1
    with pytest.raises(UserError, match="unknown shape_scans class"):
        shape_scans(classes=["sofa"], cache_dir=str(tmp_path))
    with pytest.raises(UserError, match="elevation"):
        shape_scans(elevation=[50, 10], cache_dir=str(tmp_path))
    for bad in ({"clutter": 1.5}, {"occlusion": -0.1}, {"occluder_radius": [0.6, 0.2]}):
        with pytest.raises(UserError, match="data.clutter"):
            shape_scans(cache_dir=str(tmp_path), **bad)
