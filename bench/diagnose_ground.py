"""Where a surface run on the development scene ``ground`` goes wrong: phantom area by height,
and how flat the striped slab's top came out.

    python bench/diagnose_ground.py RUN_DIR [--scene outputs/.cache/bench_scenes/ground] [--rays 300]

Reads ``RUN_DIR/mesh.ply`` (the culled mesh a volsdf or train_nerf run writes) and the scene's
true ``mesh.ply``. Prints the mesh area, the phantom share (faces whose centre lies farther than
0.05 from the true surface, by area, the benchmark's definition up to sampling), the phantom
area per height band, and for the slab's top (faces with upward normals within 0.06 of its
height z = -0.52, inside |x|, |y| < 0.95, away from the tray and the cylinder) its mean height,
the height's spread and the mean angle of the face normals from +Z (flat: 0 degrees), the
faces counted equally. With ``--rays N`` (a run with ``checkpoint.pt``) it also follows up to N
training rays that truly end on the slab's open top (the plane z = -0.52, away from the tray and the
cylinder) through the run's SDF (``4001`` samples over 0.4 units around the true hit) and prints the median
height of the first zero crossing above the truth: the learnt field's surface, not the mesh's.
A diagnosis aid for ``ground`` only: its object positions are written in.
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
    ap.add_argument("--rays", type=int, default=0, help="also follow this many training rays through the run's SDF")
    args = ap.parse_args()
    if args.rays > 0:
        print(f"field: first zero crossing above the slab's true top, median over "
              f"{'%d rays: %+.4f' % zero_crossing_height(args.run, args.scene, args.rays)}")
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


def zero_crossing_height(run: Path, scene: Path, n_rays: int, seed: int = 0):
    """(rays used, median height (world units) of the run's first SDF zero crossing above the slab's
    true top) along up to ``n_rays`` random training rays (every 20th training camera) whose true first hit
    is the slab's open top."""
    from l3d_app.geometry.rays import camera_rays
    from volsdf_run import load_sdf_field

    _, data, model = load_sdf_field(run, scene)
    o, d = (x.reshape(-1, 3).double() for x in camera_rays(data.cameras[data.train][::20]))
    t_true = (SLAB_TOP - o[:, 2]) / d[:, 2]
    hit = o + t_true[:, None] * d
    away = ((hit[:, :2] - torch.tensor([-0.45, 0.4], dtype=torch.float64)).norm(dim=1) > 0.75) \
        & ((hit[:, :2] - torch.tensor([0.45, 0.1], dtype=torch.float64)).norm(dim=1) > 0.6)
    keep = torch.nonzero((hit[:, :2].abs().amax(1) < 0.9) & away & (d[:, 2] < -0.3)).reshape(-1)
    keep = keep[torch.randperm(len(keep), generator=torch.Generator().manual_seed(seed))[:n_rays]]
    o, d, t_true = o[keep], d[keep], t_true[keep]
    ts = t_true[:, None] + torch.linspace(-0.3, 0.1, 4001, dtype=torch.float64)[None]
    with torch.no_grad():
        f = model.sdf((o[:, None] + ts[..., None] * d[:, None]).float().reshape(-1, 3)).reshape(ts.shape).double()
    enters = (f[:, 1:] < 0) & (f[:, :-1] >= 0)
    found = enters.any(1)
    i = enters.float().argmax(1, keepdim=True)
    f0, f1 = f.gather(1, i)[:, 0], f.gather(1, i + 1)[:, 0]
    t0 = ts.gather(1, i)[:, 0] + (ts[:, 1] - ts[:, 0]) * f0 / (f0 - f1)
    above = (t_true - t0) * -d[:, 2]                                     # along the ray -> height (the plane is flat)
    return int(found.sum()), float(above[found].median())


if __name__ == "__main__":
    main()
