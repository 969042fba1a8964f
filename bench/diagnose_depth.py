"""Is a surface run's phantom visible or hidden? Depth of its mesh against the truth in the
training views.

    python bench/diagnose_depth.py RUN_DIR --scene outputs/.cache/bench_scenes/ground [--every 5] [--field]

Renders camera-Z depth maps (one ray per pixel centre, ``true_depth_maps``) of the run's culled
``mesh.ply`` and of the scene's true ``mesh.ply`` from every ``--every``-th TRAINING camera and
prints, over the pixels both cover, the share where the learnt surface lies more than
``--tol`` (world units, the benchmark's phantom distance 0.05) in FRONT of the truth (a visible
phantom: a filled concavity, a web between objects, a mound the views should have carved) and
BEHIND it (a hole or a sunken surface), the median |depth error|, and the pixels only one mesh
covers. With ``--png`` it also writes the depth maps and a red (in front) / blue (behind) error
picture, one row per view (at most 4). With ``--field`` (a run with ``checkpoint.pt``, loaded as
``render_path`` loads it) it also volume-renders the trained field in the same views and reports
whether the renderer sees what the mesh shows there (its depth within ``--agree`` of the mesh's on
the in-front pixels) and the photometric error on the in-front pixels against the other covered
ones: a phantom the images pay for is a local minimum of training, one they do not pay for is a
shape the images allow. A diagnosis aid for development scenes; run by hand.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Optional

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


def field_split(field_depth: torch.Tensor, field_alpha: torch.Tensor, color: torch.Tensor, target: torch.Tensor,
                mesh_depth: torch.Tensor, truth_depth: torch.Tensor, tol: float, agree: float,
                region: Optional[torch.Tensor] = None) -> dict:
    """The rendered field on a mesh's in-front pixels. Depths and ``field_alpha`` (B, H, W), colours
    (B, H, W, 3) in [0, 1]. Pixels: both meshes cover them and the field's opacity is > 0.5;
    ``front``: of those, where the mesh lies more than ``tol`` in front of the truth. Returns
    ``front_pixels``, ``field_sees`` (share of front pixels where the field's depth is within
    ``agree`` of the mesh's), ``mse_front`` / ``mse_rest`` (mean squared colour error on the front
    pixels / the other pixels; nan where there are none). ``region`` (B, H, W) bool: count only
    those pixels (say, where one part of the true scene is the first surface)."""
    covered = torch.isfinite(mesh_depth) & torch.isfinite(truth_depth) & (field_alpha > 0.5)
    if region is not None:
        covered = covered & region
    front = covered & (mesh_depth - truth_depth < -tol)
    rest = covered & ~front
    err = ((color - target) ** 2).mean(-1)
    nan = float("nan")
    n_front = int(front.sum())
    return {"front_pixels": n_front,
            "field_sees": float(((field_depth - mesh_depth).abs() <= agree)[front].float().mean()) if n_front else nan,
            "mse_front": float(err[front].mean()) if n_front else nan,
            "mse_rest": float(err[rest].mean()) if int(rest.sum()) else nan}


def nearest_part(part_depths: torch.Tensor, truth_depth: torch.Tensor) -> torch.Tensor:
    """(P, B, H, W) depth maps of the scene's parts (+inf where a part covers no pixel) and the whole
    truth's (B, H, W) -> (B, H, W) index of the part that is the first surface (-1 where none is)."""
    gap = (part_depths - truth_depth[None]).abs()
    gap = torch.where(torch.isfinite(gap), gap, torch.full_like(gap, math.inf))
    best = gap.argmin(0)
    return torch.where(torch.isfinite(truth_depth) & torch.isfinite(gap.min(0).values), best, torch.full_like(best, -1))


def main() -> None:
    from l3d_app.data.nerf_formats import blender
    from l3d_app.geometry.mesh_io import load_mesh
    from l3d_app.render.mesh.rgbd import true_depth_maps

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--scene", type=Path, required=True, help="a make_scenes.py scene folder (NeRF-synthetic + mesh.ply)")
    ap.add_argument("--every", type=int, default=5, help="every n-th training camera")
    ap.add_argument("--tol", type=float, default=0.05, help="world units")
    ap.add_argument("--png", type=Path, default=None)
    ap.add_argument("--field", action="store_true", help="also volume-render the run's checkpoint in these views")
    ap.add_argument("--agree", type=float, default=0.02, help="--field: field and mesh depth agree within this")
    args = ap.parse_args()
    data = blender(root=str(args.scene), mesh_path="mesh.ply")
    cams = data.cameras[data.train][:: max(int(args.every), 1)]
    truth = true_depth_maps(load_mesh(str(args.scene / "mesh.ply")), cams, scale=1)
    mesh = true_depth_maps(load_mesh(str(args.run / "mesh.ply")), cams, scale=1)
    s = depth_error_shares(mesh, truth, float(args.tol))
    print(f"{len(cams)} training views, {s['pixels']} pixels both cover: learnt surface in front of the truth "
          f"by > {args.tol}: {100 * s['front']:.1f}%, behind: {100 * s['behind']:.1f}%, median |error| "
          f"{s['median_abs']:.4f}; pixels only the mesh covers {s['mesh_only']}, only the truth {s['truth_only']}")
    if args.field:
        from l3d_app.tasks.render_path import load_run

        render, _, kind = load_run(args.run, torch.device("cpu"), 8192)
        with torch.no_grad():
            out = render(cams)
        shape = mesh.shape
        target = data.images[data.train][:: max(int(args.every), 1)]
        f = field_split(out["depth"].reshape(shape), out["alpha"].reshape(shape), out["color"].reshape(*shape, 3),
                        target, mesh, truth, float(args.tol), float(args.agree))
        psnr = lambda mse: -10.0 * math.log10(mse) if mse > 0 else math.inf  # noqa: E731
        print(f"{kind} field, on the {f['front_pixels']} in-front pixels (field opacity > 0.5): its depth within "
              f"{args.agree} of the mesh's on {100 * f['field_sees']:.1f}%; colour MSE {f['mse_front']:.4f} "
              f"({psnr(f['mse_front']):.1f} dB) against {f['mse_rest']:.4f} ({psnr(f['mse_rest']):.1f} dB) on the other covered pixels")
        parts = sorted((args.scene / "parts").glob("part_*.ply"))
        if parts:  # make_scenes.py keeps each object: split the pixels by which one is truly seen first
            which = nearest_part(torch.stack([true_depth_maps(load_mesh(str(q)), cams, scale=1) for q in parts]), truth)
            for i, q in enumerate(parts):
                g = field_split(out["depth"].reshape(shape), out["alpha"].reshape(shape), out["color"].reshape(*shape, 3),
                                target, mesh, truth, float(args.tol), float(args.agree), region=which == i)
                share = g["front_pixels"] / max(f["front_pixels"], 1)
                print(f"  where {q.stem} is the true first surface: {g['front_pixels']} in-front pixels ({100 * share:.0f}%), "
                      f"colour MSE {g['mse_front']:.4f} there against {g['mse_rest']:.4f} on its other pixels")
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
