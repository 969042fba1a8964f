"""Write posed images and a coloured point set as a COLMAP folder (``images/`` +
``sparse/0/`` in text or binary layout), e.g. to export a scene we know exactly
(``export_multiview``) and train on it through ``data=colmap``.

One PINHOLE camera per image; images carry no 2D observations and points no tracks (our
reader and COLMAP's accept both). Layouts as in :mod:`l3d_app.data.colmap_model`.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.runtime.media import save_png


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations -> (N, 4) unit quaternions (w, x, y, z), w >= 0 (eigenvector method)."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    out = np.empty((len(R), 4))
    for i, m in enumerate(R):       # N is the number of images: a few hundred 4x4 eigenproblems
        (r11, r12, r13), (r21, r22, r23), (r31, r32, r33) = m
        k = np.array([[r11 - r22 - r33, 0, 0, 0], [r21 + r12, r22 - r11 - r33, 0, 0],
                      [r31 + r13, r32 + r23, r33 - r11 - r22, 0],
                      [r32 - r23, r13 - r31, r21 - r12, r11 + r22 + r33]]) / 3.0
        w, v = np.linalg.eigh(k)
        q = v[[3, 0, 1, 2], np.argmax(w)]
        out[i] = q if q[0] >= 0 else -q
    return out


def write_colmap(folder, cams: Cameras, images: Optional[torch.Tensor], points: torch.Tensor,
                 colors: Optional[torch.Tensor] = None, names: Optional[Sequence[str]] = None,
                 binary: bool = True) -> Path:
    """Write ``folder/images/*.png`` (when ``images`` (N, H, W, 3) is given) and
    ``folder/sparse/0/{cameras,images,points3D}.{bin|txt}``.

    cams: N cameras (internal convention = COLMAP's); points (P, 3) world units; colors (P, 3) in [0, 1].
    """
    folder = Path(folder)
    n = cams.batch_size
    names = list(names) if names is not None else [f"{i:05d}.png" for i in range(n)]
    if images is not None:
        (folder / "images").mkdir(parents=True, exist_ok=True)
        for i in range(n):
            save_png(folder / "images" / names[i], images[i])
    sp = folder / "sparse" / "0"
    sp.mkdir(parents=True, exist_ok=True)
    c = cams.to(device="cpu", dtype=torch.float64)
    q, t = rotmat_to_qvec(c.R.numpy()), c.t.numpy()
    K = np.stack([c.fx.numpy(), c.fy.numpy(), c.cx.numpy(), c.cy.numpy()], -1)
    P = points.detach().double().cpu().numpy().reshape(-1, 3)
    rgb = np.zeros((len(P), 3), np.uint8) if colors is None else \
        np.clip(np.round(colors.detach().float().cpu().numpy() * 255), 0, 255).astype(np.uint8)
    W, H = cams.width, cams.height
    for sub in ("cameras", "images", "points3D"):
        for ext in (".bin", ".txt"):
            (sp / f"{sub}{ext}").unlink(missing_ok=True)
    if binary:
        with open(sp / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", n))
            for i in range(n):
                f.write(struct.pack("<iiQQ4d", i + 1, 1, W, H, *K[i]))
        with open(sp / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", n))
            for i in range(n):
                f.write(struct.pack("<i7di", i + 1, *q[i], *t[i], i + 1) + names[i].encode() + b"\x00"
                        + struct.pack("<Q", 0))
        rec = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("err", "<f8"), ("len", "<u8")])
        arr = np.zeros(len(P), rec)
        arr["id"], arr["xyz"], arr["rgb"] = np.arange(1, len(P) + 1), P, rgb
        with open(sp / "points3D.bin", "wb") as f:
            f.write(struct.pack("<Q", len(P)) + arr.tobytes())
    else:
        (sp / "cameras.txt").write_text("".join(
            f"{i + 1} PINHOLE {W} {H} {' '.join(repr(float(v)) for v in K[i])}\n" for i in range(n)))
        (sp / "images.txt").write_text("".join(
            f"{i + 1} {' '.join(repr(float(v)) for v in q[i])} {' '.join(repr(float(v)) for v in t[i])} {i + 1} {names[i]}\n\n"
            for i in range(n)))
        (sp / "points3D.txt").write_text("".join(
            f"{k + 1} {float(P[k, 0])!r} {float(P[k, 1])!r} {float(P[k, 2])!r} {rgb[k, 0]} {rgb[k, 1]} {rgb[k, 2]} 0.0\n"
            for k in range(len(P))))
    return folder
