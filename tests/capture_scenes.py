"""Tiny photo sets for structure-from-motion tests, drawn by exact ray casting (numpy), independent of l3d_app.

A "corner" is three textured squares meeting at the origin (floor z=0, walls x=0 and y=0, side
2 units), each with its own seeded multi-scale noise texture: a non-planar scene with features
everywhere. :func:`corner_views` photographs it from cameras on an arc around the corner.
"""

from __future__ import annotations

from pathlib import Path
from typing import List

import numpy as np


def _texture(rng: np.random.Generator, n: int = 256) -> np.ndarray:
    """(n, n, 3) float texture: blocky multi-scale random colour noise (corners for SIFT)."""
    out = np.zeros((n, n, 3))
    for cells, w in ((4, 0.5), (8, 0.35), (16, 0.3), (32, 0.25), (64, 0.15)):
        g = rng.random((cells, cells, 3))
        out += w * np.kron(g, np.ones((n // cells, n // cells, 1)))
    return (out - out.min()) / (out.max() - out.min())


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(3, 3) camera-to-world rotation, OpenCV axes (+x right, +y down, +z forward), world up +z."""
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    return np.stack([r, d, f], 1)


def corner_eyes(n: int, az_range=(10.0, 80.0), radius: float = 3.2, z: float = 1.6) -> np.ndarray:
    """(n, 3) camera centres of :func:`corner_views`: an arc at ``radius`` and height ``z``."""
    az = np.radians(np.linspace(*az_range, n))
    return np.stack([radius * np.cos(az), radius * np.sin(az), np.full(n, z)], 1)


def corner_views(seed: int, n: int, width: int = 200, height: int = 150, az_range=(10.0, 80.0),
                 radius: float = 3.2, z: float = 1.6) -> List[np.ndarray]:
    """``n`` (height, width, 3) uint8 views of the corner with textures from ``seed``."""
    rng = np.random.default_rng(seed)
    tex = [_texture(rng) for _ in range(3)]
    f = 0.9 * width
    v, u = np.mgrid[0:height, 0:width] + 0.5
    dirs_cam = np.stack([(u - width / 2) / f, (v - height / 2) / f, np.ones_like(u)], -1)
    views = []
    for eye in corner_eyes(n, az_range, radius, z):
        d = dirs_cam @ _look_at(eye, np.array([0.5, 0.5, 0.5])).T          # (H, W, 3) world directions
        img, best = np.zeros((height, width, 3)), np.full((height, width), np.inf)
        for axis, t in enumerate(tex):                                       # plane coordinate[axis] = 0
            with np.errstate(divide="ignore", invalid="ignore"):
                s = -eye[axis] / d[..., axis]
            p = eye + s[..., None] * d
            others = [k for k in range(3) if k != axis]
            a, b = p[..., others[0]], p[..., others[1]]
            hit = (s > 0) & (a >= 0) & (a <= 2) & (b >= 0) & (b <= 2) & (s < best)
            ia = np.clip((a / 2 * (t.shape[0] - 1)).astype(int), 0, t.shape[0] - 1)
            ib = np.clip((b / 2 * (t.shape[1] - 1)).astype(int), 0, t.shape[1] - 1)
            img[hit] = t[ia[hit], ib[hit]]
            best = np.where(hit, s, best)
        img[np.isinf(best)] = (0.55, 0.6, 0.7)
        views.append((img * 255).round().astype(np.uint8))
    return views


def write_views(folder: Path, views: List[np.ndarray], prefix: str = "view", suffix: str = ".png") -> List[Path]:
    """Write ``views`` as ``prefix_000.png`` ... into ``folder`` (created); returns the paths."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, v in enumerate(views):
        p = folder / f"{prefix}_{i:03d}{suffix}"
        Image.fromarray(v).save(p, quality=95) if suffix == ".jpg" else Image.fromarray(v).save(p)
        paths.append(p)
    return paths
