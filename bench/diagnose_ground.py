"""Where a surface run on the development scene ``ground`` goes wrong: phantom area by height,
and how flat the striped slab's top came out.

    python bench/diagnose_ground.py RUN_DIR [--scene outputs/.cache/bench_scenes/ground]

Reads ``RUN_DIR/mesh.ply`` (the culled mesh a volsdf or train_nerf run writes) and the scene's
true ``mesh.ply``. Prints the mesh area, the phantom share (faces whose centre lies farther than
0.05 from the true surface, by area, the benchmark's definition up to sampling), the phantom
area per height band, and for the slab's top (faces with upward normals within 0.06 of its
height z = -0.52, inside |x|, |y| < 0.95, away from the tray and the cylinder) its mean height,
the height's spread and the mean angle of the face normals from +Z (flat: 0 degrees), the
faces counted equally. A diagnosis aid for ``ground`` only: its object positions are written in.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing
SLAB_TOP = -0.52


def main() -> None:
    from l3d_app.geometry.mesh_io import load_mesh
    from l3d_app.geometry.point_mesh_distance import point_mesh_distance

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--scene", type=Path, default=REPO / "outputs" / ".cache" / "bench_scenes" / "ground")
    args = ap.parse_args()
    truth = load_mesh(str(args.scene / "mesh.ply")).to(dtype=torch.float64)
    mesh = load_mesh(str(args.run / "mesh.ply")).to(dtype=torch.float64)
    tri = mesh.verts[mesh.faces]                                         # (F, 3, 3)
    centre = tri.mean(1)
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * cross.norm(dim=-1)
    normal = cross / cross.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    far = point_mesh_distance(centre, truth).distance > 0.05
    c, a, n = centre.numpy(), area.numpy(), normal.numpy()
    far = far.numpy()
    print(f"mesh area {a.sum():.3f}, phantom share {a[far].sum() / a.sum():.3f}")
    for lo, hi in [(-9, -0.6), (-0.6, -0.5), (-0.5, -0.2), (-0.2, 0.1), (0.1, 9)]:
        sel = far & (c[:, 2] >= lo) & (c[:, 2] < hi)
        print(f"  phantom area with z in [{lo}, {hi}): {a[sel].sum():.3f} ({int(sel.sum())} faces)")
    near_objects = ((np.hypot(c[:, 0] - 0.45, c[:, 1] - 0.1) < 0.3)                   # the cylinder
                    | (np.abs(c[:, 0] + 0.45) + np.abs(c[:, 1] - 0.4) < 0.5))          # the tray
    top = ((n[:, 2] > 0.5) & (np.abs(c[:, 2] - SLAB_TOP) < 0.06) & (np.abs(c[:, :2]).max(1) < 0.95)
           & ~near_objects)
    z = c[top, 2]
    tilt = np.degrees(np.arccos(np.clip(n[top, 2], -1.0, 1.0)))
    print(f"slab top: {int(top.sum())} faces, area {a[top].sum():.3f}, z mean {z.mean():+.4f} (true {SLAB_TOP}), "
          f"z std {z.std():.4f}, normal tilt mean {tilt.mean():.1f} deg")


if __name__ == "__main__":
    main()
