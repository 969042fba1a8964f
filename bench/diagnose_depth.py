"""Is a surface run's phantom visible or hidden? Depth of its mesh against the truth in the
training views.

    python bench/diagnose_depth.py RUN_DIR --scene outputs/.cache/bench_scenes/ground [--every 5]

Renders camera-Z depth maps (one ray per pixel centre, ``true_depth_maps``) of the run's culled
``mesh.ply`` and of the scene's true ``mesh.ply`` from every ``--every``-th TRAINING camera and
prints, over the pixels both cover, the share where the learnt surface lies more than
``--tol`` (world units, the benchmark's phantom distance 0.05) in FRONT of the truth (a visible
phantom: a filled concavity, a web between objects, a mound the views should have carved) and
BEHIND it (a hole or a sunken surface), the median |depth error|, and the pixels only one mesh
covers. With ``--png`` it also writes the depth maps and a red (in front) / blue (behind) error
picture, one row per view (at most 4). A diagnosis aid for development scenes; run by hand.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing


def depth_error_shares(mesh_depth: torch.Tensor, truth_depth: torch.Tensor, tol: float) -> dict:
    """Shares of (B, H, W) depth maps (+inf where uncovered): ``front`` / ``behind`` = fraction of
    the pixels both cover where mesh depth < truth - tol / > truth + tol; ``median_abs`` over
    those pixels (world units); ``mesh_only`` / ``truth_only`` pixel counts."""
    mesh_hit, truth_hit = torch.isfinite(mesh_depth), torch.isfinite(truth_depth)
    both = mesh_hit & truth_hit
    err = (mesh_depth - truth_depth)[both]
    n = max(int(both.sum()), 1)
    return {"pixels": int(both.sum()),
            "front": float((err < -tol).sum()) / n, "behind": float((err > tol).sum()) / n,
            "median_abs": float(err.abs().median()) if err.numel() else float("nan"),
            "mesh_only": int((mesh_hit & ~truth_hit).sum()), "truth_only": int((truth_hit & ~mesh_hit).sum())}


def main() -> None:
    from l3d_app.data.nerf_formats import blender
    from l3d_app.geometry.mesh_io import load_mesh
    from l3d_app.render.rgbd import true_depth_maps

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--scene", type=Path, required=True, help="a make_scenes.py scene folder (NeRF-synthetic + mesh.ply)")
    ap.add_argument("--every", type=int, default=5, help="every n-th training camera")
    ap.add_argument("--tol", type=float, default=0.05, help="world units")
    ap.add_argument("--png", type=Path, default=None)
    args = ap.parse_args()
    data = blender(root=str(args.scene), mesh_path="mesh.ply")
    cams = data.cameras[data.train][:: max(int(args.every), 1)]
    truth = true_depth_maps(load_mesh(str(args.scene / "mesh.ply")), cams, scale=1)
    mesh = true_depth_maps(load_mesh(str(args.run / "mesh.ply")), cams, scale=1)
    s = depth_error_shares(mesh, truth, float(args.tol))
    print(f"{len(cams)} training views, {s['pixels']} pixels both cover: learnt surface in front of the truth "
          f"by > {args.tol}: {100 * s['front']:.1f}%, behind: {100 * s['behind']:.1f}%, median |error| "
          f"{s['median_abs']:.4f}; pixels only the mesh covers {s['mesh_only']}, only the truth {s['truth_only']}")
    if args.png is not None:
        from l3d_app.runtime.media import save_png

        rows = []
        for i in range(min(4, len(cams))):
            panels = []
            for d in (truth[i], mesh[i]):
                fin = torch.isfinite(d)
                lo, hi = d[fin].min(), d[fin].max()
                panels.append(torch.where(fin, (d - lo) / (hi - lo).clamp_min(1e-9), torch.ones_like(d))[..., None].expand(-1, -1, 3))
            e = torch.nan_to_num(mesh[i] - truth[i], nan=0.0, posinf=0.0, neginf=0.0)
            err = torch.stack([(-e).clamp(0, 0.3) / 0.3, torch.zeros_like(e), e.clamp(0, 0.3) / 0.3], -1)
            rows.append(torch.cat(panels + [err], dim=1))
        save_png(args.png, torch.cat(rows, dim=0))
        print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
