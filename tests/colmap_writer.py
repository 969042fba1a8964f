"""Test helper, independent of l3d_app's reader: write a known scene in COLMAP's text and binary
layouts (``struct`` packing straight from COLMAP's documentation), with distorted observations."""

from __future__ import annotations

import struct
from pathlib import Path

import imageio.v2 as imageio
import numpy as np

MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "OPENCV_FISHEYE": 5}


def rot_to_quat(R):
    """3x3 rotation -> (w, x, y, z), w >= 0 (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


def params_for(model, fx, fy, cx, cy, dist):
    """COLMAP parameter list; dist = (k1, k2, p1, p2) as the model allows."""
    k1, k2, p1, p2 = dist
    return {"SIMPLE_PINHOLE": [fx, cx, cy], "PINHOLE": [fx, fy, cx, cy], "SIMPLE_RADIAL": [fx, cx, cy, k1],
            "RADIAL": [fx, cx, cy, k1, k2], "OPENCV": [fx, fy, cx, cy, k1, k2, p1, p2],
            "OPENCV_FISHEYE": [fx, fy, cx, cy, k1, k2, 0.0, 0.0]}[model]


def distort_np(x, y, k1, k2, p1, p2):
    r2 = x * x + y * y
    rad = k1 * r2 + k2 * r2 * r2
    return x + x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y + y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def undistort_np(xd, yd, k1, k2, p1, p2, iters=50):
    """Fixed-point inverse (test side; independent of the library's Newton)."""
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        dx, dy = distort_np(x, y, k1, k2, p1, p2)
        x, y = x - (dx - xd), y - (dy - yd)
    return x, y


def pattern(x, y):
    """Smooth RGB in [0, 1] of normalised pinhole coordinates (what a pinhole image shows)."""
    return np.stack([0.5 + 0.4 * np.sin(5 * x), 0.5 + 0.4 * np.cos(4 * y), 0.5 + 0.3 * np.sin(3 * x + 3 * y)], -1)


def write_scene(root, R, t, K, size, points, colors, model="PINHOLE", dist=(0, 0, 0, 0), names=None,
                binary=True, text=True, image_dir="images", image_scale=1):
    """Write images (showing :func:`pattern` through the given distortion) and sparse/0 models.

    R (N,3,3), t (N,3) world->camera (OpenCV); K (N,4) fx, fy, cx, cy (one camera per image);
    size (W, H); points (P,3); colors (P,3) uint8. Observations = distorted projections.
    """
    root = Path(root)
    N = len(R)
    names = names or [f"img_{i:03d}.png" for i in range(N)]
    W, H = size
    obs = []
    for i in range(N):
        pc = points @ R[i].T + t[i]
        x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        xd, yd = distort_np(x, y, *dist)
        obs.append(np.stack([K[i, 0] * xd + K[i, 2], K[i, 1] * yd + K[i, 3]], -1))
        # image: pixel centre (u, v) in the distorted frame shows pattern(undistorted coords)
        Ws, Hs = W // image_scale, H // image_scale
        v, u = np.meshgrid(np.arange(Hs) + 0.5, np.arange(Ws) + 0.5, indexing="ij")
        u, v = u * image_scale, v * image_scale
        xu, yu = undistort_np((u - K[i, 2]) / K[i, 0], (v - K[i, 3]) / K[i, 1], *dist)
        (root / image_dir).mkdir(parents=True, exist_ok=True)
        imageio.imwrite(root / image_dir / names[i], np.round(pattern(xu, yu) * 255).astype(np.uint8))
    sp = root / "sparse" / "0"
    sp.mkdir(parents=True, exist_ok=True)
    quats = [rot_to_quat(R[i]) for i in range(N)]
    pids = np.arange(1, len(points) + 1)
    if text:
        with open(sp / "cameras.txt", "w") as f:
            f.write("# Camera list\n")
            for i in range(N):
                f.write(f"{i + 1} {model} {W} {H} " + " ".join(repr(float(p)) for p in params_for(model, *K[i], dist)) + "\n")
        with open(sp / "images.txt", "w") as f:
            f.write("# Image list with two lines of data per image:\n")
            for i in range(N):
                f.write(" ".join([str(i + 1)] + [repr(float(v)) for v in quats[i]] + [repr(float(v)) for v in t[i]]
                                 + [str(i + 1), names[i]]) + "\n")
                f.write(" ".join(f"{a!r} {b!r} {int(p)}" for (a, b), p in zip(obs[i].tolist(), pids)) + "\n")
        with open(sp / "points3D.txt", "w") as f:
            for p, (xyz, c) in enumerate(zip(points, colors)):
                track = " ".join(f"{i + 1} {p}" for i in range(N))
                f.write(f"{pids[p]} {float(xyz[0])!r} {float(xyz[1])!r} {float(xyz[2])!r} {c[0]} {c[1]} {c[2]} 0.5 {track}\n")
    if binary:
        with open(sp / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", N))
            for i in range(N):
                prm = params_for(model, *K[i], dist)
                f.write(struct.pack("<iiQQ", i + 1, MODEL_IDS[model], W, H) + struct.pack(f"<{len(prm)}d", *prm))
        with open(sp / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", N))
            for i in range(N):
                f.write(struct.pack("<i7di", i + 1, *quats[i], *t[i], i + 1) + names[i].encode() + b"\x00")
                f.write(struct.pack("<Q", len(points)))
                for (a, b), p in zip(obs[i].tolist(), pids):
                    f.write(struct.pack("<ddq", a, b, int(p)))
        with open(sp / "points3D.bin", "wb") as f:
            f.write(struct.pack("<Q", len(points)))
            for p, (xyz, c) in enumerate(zip(points, colors)):
                f.write(struct.pack("<Q3d3Bd", int(pids[p]), *xyz, *[int(v) for v in c], 0.5))
                f.write(struct.pack("<Q", N) + b"".join(struct.pack("<ii", i + 1, p) for i in range(N)))
    return obs
