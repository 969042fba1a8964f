"""Built-in procedural scans: 12 classes of objects, some differing in one part, seen by a single-view
scanner (partial) with noise, every point labelled with its part.

Classes (:data:`CLASS_NAMES`) and the part that separates the confusable ones::

    chair     seat, back, legs            armchair  = chair + arms       stool = chair - back (smaller seat)
    table     top, legs (wide, thin top)  bench     long low seat, legs
    vase      body, neck, foot            bottle    body, long thin neck, no foot
    cup       body                        mug       = cup + handle       bowl  wide low body, foot
    lamp      lamp base, straight stem, shade         desk_lamp = lamp with a bent stem

Part labels (:data:`PART_NAMES`, one space for all classes): seat, back, legs, arms, top, body, neck,
foot, handle, lamp_base, stem, shade, and background (what surrounds the object in a cluttered scan).

Each object is assembled from primitive meshes (its own seed fixes every size and style) and scanned by
:func:`l3d_app.data.scanner.scan_object`: a viewpoint at a random azimuth and an elevation in
``elevation`` degrees, an orthographic z-buffer of ``scan_grid`` cells across the object (depth tolerance
``scan_tolerance``) keeps what the scanner sees, ``num_points`` of it are drawn, centred, scaled to the
unit ball and given Gaussian noise of ``noise`` (in those units). With probability ``clutter`` the object
stands among clutter (:func:`surroundings`): a neighbour of a random class beside it and, seen from above,
the floor; clutter in front hides the object, and what lies in the object's widened bounding box stays in
the scan as background. With probability ``occlusion`` a disc in the scanner's image plane (radius uniform
in ``occluder_radius``, at most 60% of the view) hides a further part. A mug seen from the side its handle
is not on, or with its handle hidden, is a cup: some clouds are ambiguous by construction.

Generated on first use and cached as ``shape_scans_<hash>.npz`` in ``cache_dir`` (default
``~/.cache/l3d_app``); the hash covers every generation knob. Object ``i`` of class ``c`` is seeded by
``(seed, c, i)``; the first ``train_per_class`` of each class are train, the rest test; validation is
``val_fraction`` of train (per class, ``val_seed``).
"""

from __future__ import annotations

import math
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from l3d_app.data.point_cache import cached_point_sets, class_block_splits
from l3d_app.data.point_sets import PointCloudData
from l3d_app.data.scanner import Part, scan_object
from l3d_app.data.shape_parts import arm_rests, lathe
from l3d_app.errors import UserError
from l3d_app.geometry import primitives as prim
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.transforms import axis_rotation
from l3d_app.registry import DATASETS
from l3d_app.runtime.config_values import config_floats, config_words
from l3d_app.runtime.progress import progress

CLASS_NAMES = ("chair", "armchair", "stool", "table", "bench", "vase", "bottle", "cup", "mug", "bowl", "lamp",
               "desk_lamp")
PART_NAMES = ("seat", "back", "legs", "arms", "top", "body", "neck", "foot", "handle", "lamp_base", "stem", "shade",
              "background")
SEAT, BACK, LEGS, ARMS, TOP, BODY, NECK, FOOT, HANDLE, LBASE, STEM, SHADE, BACKGROUND = range(13)
VERSION = 2  # bump when the generators change (invalidates caches)


def _box(center, size) -> Mesh:
    return prim.box([float(c) for c in center], [float(s) for s in size])


def _cyl(center, radius, height, n: int = 14) -> Mesh:
    return prim.transformed(prim.cylinder(float(radius), float(height), n), translation=[float(c) for c in center])


def _legs(rng, w: float, d: float, h: float, thick: float, inset: float, splay: float = 0.0) -> List[Part]:
    """Four legs under a w x d rectangle from the floor to height h (round or square, optionally splayed)."""
    round_legs = rng.random() < 0.5
    out = []
    for sx in (-1, 1):
        for sz in (-1, 1):
            x, z = sx * (w / 2 - thick / 2 - inset), sz * (d / 2 - thick / 2 - inset)
            leg = _cyl((0, 0, 0), thick / 2, h, 10) if round_legs else _box((0, 0, 0), (thick, h, thick))
            rot = axis_rotation("z", -sx * splay) @ axis_rotation("x", sz * splay)
            out.append((prim.transformed(leg, rotation=rot, translation=(x, h / 2, z)), LEGS))
    return out


def _seating(rng, back: bool, arms: bool, w: float, d: float, h: float) -> List[Part]:
    """A seat at height h on four legs, with a back and arms when asked."""
    t = rng.uniform(0.06, 0.12)
    parts: List[Part] = [(_box((0, h - t / 2, 0), (w, t, d)), SEAT)]
    parts += _legs(rng, w, d, h - t, rng.uniform(0.05, 0.09), rng.uniform(0.0, 0.06))
    if back:
        bh, bt = rng.uniform(0.6, 1.0), rng.uniform(0.05, 0.09)
        rot = axis_rotation("x", -rng.uniform(0.0, 15.0))
        if rng.random() < 0.6:
            pieces = [_box((0, bh / 2, 0), (w, bh, bt))]
        else:
            post = rng.uniform(0.05, 0.08)
            pieces = [_box((sx * (w / 2 - post / 2), bh / 2, 0), (post, bh, bt)) for sx in (-1, 1)]
            slats = int(rng.integers(2, 5))
            pieces += [_box((0, bh * (0.3 + 0.7 * (k + 0.5) / slats), 0), (w - 2 * post, bh * 0.12, bt * 0.8))
                       for k in range(slats)]
        parts += [(prim.transformed(p, rotation=rot, translation=(0.0, h, -d / 2 + bt / 2)), BACK) for p in pieces]
    if arms:
        parts += arm_rests(rng, w, d, h, ARMS)
    return parts


def _chair(rng) -> List[Part]:
    return _seating(rng, True, False, rng.uniform(0.8, 1.1), rng.uniform(0.75, 1.05), rng.uniform(0.75, 1.0))


def _armchair(rng) -> List[Part]:
    return _seating(rng, True, True, rng.uniform(0.8, 1.1), rng.uniform(0.75, 1.05), rng.uniform(0.75, 1.0))


def _stool(rng) -> List[Part]:
    w = rng.uniform(0.45, 0.7)
    h = rng.uniform(0.8, 1.2)
    if rng.random() < 0.5:                          # round seat, splayed legs
        t = rng.uniform(0.06, 0.1)
        parts: List[Part] = [(_cyl((0, h - t / 2, 0), w / 2, t, 20), SEAT)]
        parts += _legs(rng, w * 0.8, w * 0.8, h - t, rng.uniform(0.04, 0.07), 0.0, rng.uniform(3.0, 8.0))
        return parts
    return _seating(rng, False, False, w, w, h)


def _table(rng) -> List[Part]:
    w, d, h, t = rng.uniform(1.4, 2.2), rng.uniform(0.8, 1.2), rng.uniform(0.7, 0.95), rng.uniform(0.03, 0.07)
    parts: List[Part] = [(_box((0, h - t / 2, 0), (w, t, d)), TOP)]
    return parts + _legs(rng, w, d, h - t, rng.uniform(0.05, 0.1), rng.uniform(0.0, 0.15))


def _bench(rng) -> List[Part]:
    w, d, h = rng.uniform(1.6, 2.4), rng.uniform(0.35, 0.55), rng.uniform(0.4, 0.55)
    t = rng.uniform(0.06, 0.12)
    parts: List[Part] = [(_box((0, h - t / 2, 0), (w, t, d)), SEAT)]
    if rng.random() < 0.5:                           # two slab legs
        for sx in (-1, 1):
            parts.append((_box((sx * (w / 2 - 0.15), (h - t) / 2, 0), (0.06, h - t, d * 0.9)), LEGS))
        return parts
    return parts + _legs(rng, w, d, h - t, rng.uniform(0.05, 0.08), rng.uniform(0.0, 0.1))


def _vase(rng) -> List[Part]:
    foot_h, body_h, r0 = rng.uniform(0.06, 0.14), rng.uniform(0.8, 1.3), rng.uniform(0.3, 0.45)
    s = np.linspace(0.0, 1.0, 12)
    radii = r0 * (1 + rng.uniform(0.2, 0.6) * np.sin(np.pi * s)) * (1 - 0.45 * s ** 2)
    heights = foot_h + body_h * s
    parts: List[Part] = [(lathe(radii, heights, 24, cap_bottom=True), BODY)]
    neck_r, neck_h, top = radii[-1] * rng.uniform(0.8, 1.0), rng.uniform(0.15, 0.35), heights[-1]
    parts.append((lathe([radii[-1], neck_r, neck_r * rng.uniform(1.2, 1.6)],
                        [top, top + neck_h, top + neck_h + 0.06], 24), NECK))
    fr = radii[0] * rng.uniform(0.8, 1.1)
    parts.append((lathe([fr, fr, radii[0]], [0.0, foot_h * 0.6, foot_h], 24, cap_bottom=True), FOOT))
    return parts


def _bottle(rng) -> List[Part]:
    r, body_h = rng.uniform(0.22, 0.35), rng.uniform(0.8, 1.2)
    shoulder = rng.uniform(0.12, 0.25)
    neck_r, neck_h = r * rng.uniform(0.3, 0.45), rng.uniform(0.35, 0.6)
    parts: List[Part] = [(lathe([r, r, neck_r], [0.0, body_h, body_h + shoulder], 24, cap_bottom=True), BODY)]
    top = body_h + shoulder
    parts.append((lathe([neck_r, neck_r, neck_r * 1.1], [top, top + neck_h, top + neck_h + 0.03], 16, cap_top=True),
                  NECK))
    return parts


def _cup_body(rng) -> Tuple[List[Part], float, float]:
    r, h = rng.uniform(0.32, 0.45), rng.uniform(0.7, 1.0)
    taper = rng.uniform(0.75, 1.0)
    wall = 0.04
    outer = lathe([r * taper, r], [0.0, h], 24, cap_bottom=True)
    inner = lathe([r - wall, (r * taper) - wall], [h, wall], 24, cap_top=True)      # open top: the inside wall
    return [(outer, BODY), (inner, BODY)], r, h


def _cup(rng) -> List[Part]:
    return _cup_body(rng)[0]


def _mug(rng) -> List[Part]:
    parts, r, h = _cup_body(rng)
    major, minor = rng.uniform(0.18, 0.28) * h, rng.uniform(0.035, 0.06)
    ring = prim.transformed(prim.torus(major, minor, 24, 8), rotation=axis_rotation("x", 90.0))   # in the XY plane
    keep = (ring.verts[ring.faces].mean(1)[:, 0] > -minor * 0.5)          # the outer half of the ring
    half = Mesh(verts=ring.verts, faces=ring.faces[keep])
    parts.append((prim.transformed(half, translation=(r * 0.97, h * rng.uniform(0.45, 0.6), 0.0)), HANDLE))
    return parts


def _bowl(rng) -> List[Part]:
    r, h = rng.uniform(0.6, 0.9), rng.uniform(0.3, 0.5)
    a = np.linspace(0.0, np.pi / 2, 9)
    foot_h = rng.uniform(0.04, 0.08)
    outer = lathe(r * np.sin(a) * 0.999 + 1e-3, foot_h + h * (1 - np.cos(a)), 24)
    inner = lathe((r - 0.04) * np.sin(a[::-1]) + 1e-3, foot_h + 0.04 + (h - 0.04) * (1 - np.cos(a[::-1])), 24)
    fr = r * rng.uniform(0.3, 0.45)
    foot = lathe([fr, fr], [0.0, foot_h], 24, cap_bottom=True)
    return [(outer, BODY), (inner, BODY), (foot, FOOT)]


def _lamp_parts(rng, bent: bool) -> List[Part]:
    bh, br = rng.uniform(0.05, 0.12), rng.uniform(0.25, 0.4)
    parts: List[Part] = [(_cyl((0, bh / 2, 0), br, bh, 20) if rng.random() < 0.6 else
                          _box((0, bh / 2, 0), (1.8 * br, bh, 1.8 * br)), LBASE)]
    stem_h, stem_r = rng.uniform(0.8, 1.4), rng.uniform(0.025, 0.04)
    parts.append((_cyl((0, bh + stem_h / 2, 0), stem_r, stem_h, 10), STEM))
    top = np.array([0.0, bh + stem_h, 0.0])
    sh, r_top, r_bot = rng.uniform(0.3, 0.5), rng.uniform(0.1, 0.2), rng.uniform(0.25, 0.4)
    shade = lathe([r_bot, r_top], [-sh * 0.6, sh * 0.4], 24) if rng.random() < 0.6 else \
        lathe([r_bot, r_bot], [-sh * 0.6, sh * 0.4], 24)
    if bent:                                                     # a second arm at an angle, the shade tilted
        arm_l, arm_a = rng.uniform(0.45, 0.8), rng.uniform(35.0, 70.0)
        rot = axis_rotation("x", arm_a)
        parts.append((prim.transformed(_cyl((0, arm_l / 2, 0), stem_r, arm_l, 10), rotation=rot,
                                       translation=top.tolist()), STEM))
        top = top + (rot.double() @ torch.tensor([0.0, arm_l, 0.0], dtype=torch.float64)).numpy()
        shade = prim.transformed(prim.transformed(shade, rotation=axis_rotation("x", 180.0)),
                                 rotation=axis_rotation("x", arm_a + rng.uniform(60.0, 100.0)), translation=top.tolist())
    else:
        shade = prim.transformed(shade, translation=top.tolist())
    parts.append((shade, SHADE))
    return parts


GENERATORS: Dict[str, Callable[[np.random.Generator], List[Part]]] = {
    "chair": _chair, "armchair": _armchair, "stool": _stool, "table": _table, "bench": _bench, "vase": _vase,
    "bottle": _bottle, "cup": _cup, "mug": _mug, "bowl": _bowl, "lamp": lambda rng: _lamp_parts(rng, False),
    "desk_lamp": lambda rng: _lamp_parts(rng, True)}


def _footprint(parts: Sequence[Part]) -> Tuple[np.ndarray, float]:
    """The centre (2,) of the parts' bounding box on the floor (x, z) and the farthest vertex's distance from it."""
    xz = torch.cat([m.verts for m, _ in parts]).double()[:, [0, 2]].numpy()
    centre = (xz.min(0) + xz.max(0)) / 2
    return centre, float(np.linalg.norm(xz - centre, axis=1).max())


def surroundings(rng: np.random.Generator, parts: Sequence[Part], floor: bool) -> List[Part]:
    """What stands around the object made of ``parts``: a neighbour of a random class, turned about the
    vertical, its footprint 0.8-1.2 times the two footprints' radii away in a random direction, and (when
    ``floor``) the floor around the object; every part labelled background."""
    (cx, cz), r1 = _footprint(parts)
    other = GENERATORS[CLASS_NAMES[int(rng.integers(len(CLASS_NAMES)))]](rng)
    (ox, oz), r2 = _footprint(other)
    angle, dist = rng.uniform(0.0, 2 * math.pi), (r1 + r2) * rng.uniform(0.8, 1.2)
    rot = axis_rotation("y", rng.uniform(0.0, 360.0))
    out = [(prim.transformed(prim.transformed(m, translation=(-ox, 0.0, -oz)), rotation=rot,
                             translation=(cx + dist * math.cos(angle), 0.0, cz + dist * math.sin(angle))), BACKGROUND)
           for m, _ in other]
    if floor:
        out.append((_box((cx, -0.01, cz), (3.0 * r1, 0.02, 3.0 * r1)), BACKGROUND))
    return out


def generate(classes: Sequence[str], per_class: int, num_points: int, seed: int, elevation: Sequence[float],
             noise: float, oversample: int, grid: int, tolerance: float, occlusion: float = 0.0,
             occluder_radius: Tuple[float, float] = (0.25, 0.6), clutter: float = 0.0) -> Tuple[np.ndarray, ...]:
    """``per_class`` scans of each class: points (N, P, 3) float32, class labels (N,) uint8 (index in
    :data:`CLASS_NAMES`), part labels (N, P) uint8, the share of each object's surface samples in its scan
    (N,) float32; class by class."""
    pts = np.empty((len(classes) * per_class, num_points, 3), np.float32)
    parts = np.empty((len(classes) * per_class, num_points), np.uint8)
    labels = np.empty(len(classes) * per_class, np.uint8)
    seen = np.empty(len(classes) * per_class, np.float32)
    jobs = [(c, i) for c in classes for i in range(per_class)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread is faster than several
    try:
        for k, (c, i) in enumerate(progress(jobs, desc="shape_scans")):
            cid = CLASS_NAMES.index(c)
            rng = np.random.default_rng([seed, cid, i])
            gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
            azimuth, elev = rng.uniform(0.0, 360.0), rng.uniform(*elevation)
            shape = GENERATORS[c](rng)
            around = surroundings(rng, shape, elev > 0.0) if rng.random() < clutter else []
            p, lab, share = scan_object(shape, num_points, gen, azimuth, elev, oversample, grid, tolerance, noise,
                                        occlusion, occluder_radius, around)
            if share < 0.1 and around:                   # the neighbour hides the object: scan it without
                p, lab, share = scan_object(shape, num_points, gen, azimuth, elev, oversample, grid, tolerance,
                                            noise, occlusion, occluder_radius)
            pts[k], parts[k], labels[k], seen[k] = p.numpy(), lab.numpy().astype(np.uint8), cid, share
    finally:
        torch.set_num_threads(threads)
    return pts, labels, parts, seen


@DATASETS.register("shape_scans")
def shape_scans(classes: Sequence[str] = CLASS_NAMES, train_per_class: int = 100, test_per_class: int = 40,
                num_points: int = 2048, seed: int = 0, elevation: Sequence[float] = (-10.0, 50.0),
                noise: float = 0.01, clutter: float = 0.5, occlusion: float = 0.5,
                occluder_radius: Sequence[float] = (0.25, 0.6),
                oversample: int = 8, scan_grid: int = 24, scan_tolerance: float = 0.08,
                cache_dir: Optional[str] = None, val_fraction: float = 0.1, val_seed: int = 0, kind: str = "cls",
                device=None) -> PointCloudData:
    """The built-in scans (see the module docstring), generated once and cached; both label kinds present."""
    classes = config_words(classes, "data.classes")
    unknown = [c for c in classes if c not in CLASS_NAMES]
    if unknown or not classes:
        raise UserError(f"unknown shape_scans class {unknown or classes}; known: {', '.join(CLASS_NAMES)}")
    for key, value in (("train_per_class", train_per_class), ("test_per_class", test_per_class),
                       ("num_points", num_points), ("oversample", oversample), ("scan_grid", scan_grid)):
        if int(value) < 1:
            raise UserError(f"data.{key} must be >= 1, got {value}")
    lo, hi = config_floats(elevation, "data.elevation", 2)
    if not (-90.0 <= lo <= hi <= 90.0) or float(noise) < 0 or not float(scan_tolerance) > 0:
        raise UserError(f"need -90 <= data.elevation[0] <= [1] <= 90, data.noise >= 0 and data.scan_tolerance > 0; "
                        f"got {[lo, hi]}, {noise}, {scan_tolerance}")
    r_lo, r_hi = config_floats(occluder_radius, "data.occluder_radius", 2)
    if not (0.0 <= float(occlusion) <= 1.0 and 0.0 <= float(clutter) <= 1.0 and 0.0 <= r_lo <= r_hi):
        raise UserError(f"need 0 <= data.occlusion <= 1, 0 <= data.clutter <= 1 and 0 <= data.occluder_radius[0] "
                        f"<= [1]; got {occlusion}, {clutter}, {[r_lo, r_hi]}")
    n = int(train_per_class) + int(test_per_class)
    knobs = {"clutter": float(clutter), "occlusion": float(occlusion), "occluder_radius": [r_lo, r_hi],
             "classes": classes, "n": n, "num_points": int(num_points), "seed": int(seed), "elevation": [lo, hi],
             "noise": float(noise), "oversample": int(oversample), "grid": int(scan_grid),
             "tolerance": float(scan_tolerance), "v": VERSION}

    def make() -> dict:
        pts, labels, parts, seen = generate(classes, n, int(num_points), int(seed), (lo, hi), float(noise),
                                            int(oversample), int(scan_grid), float(scan_tolerance), float(occlusion),
                                            (r_lo, r_hi), float(clutter))
        return {"points": pts, "labels": labels, "parts": parts, "seen": seen}

    pts, labels, parts, path = cached_point_sets("shape_scans", knobs, cache_dir, make)
    train, test = class_block_splits(pts, labels, parts, n, int(train_per_class))
    return PointCloudData(train, test, list(CLASS_NAMES), list(PART_NAMES),
                          source=f"shape_scans:{path}").with_val(val_fraction, val_seed)
