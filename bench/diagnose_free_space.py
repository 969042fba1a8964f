"""What a volsdf run's known free space says and what its SDF did with it, on a development scene.

    python bench/diagnose_free_space.py RUN_DIR [--scene outputs/.cache/bench_scenes/ground] [--points 400000]

Needs the run's ``checkpoint.pt``, ``free_space.pt`` (a run with the free-space stage) and ``mesh.ply``.
1. The loss's points: ``--points`` drawn on the saved free stretches as volsdf draws them at the end
   (shortened by ``margin_beta`` x beta 0.005), the final SDF there: the share with ``f < 0`` and
   ``f < 0.02``, and the share of the occupancy loss's integrand (``Psi_beta(-f)`` x length) those carry.
2. On ``ground`` (its tray's position is written in): for the training rays whose true first hit is
   the tray's floor, its rim and walls, or elsewhere, the medians of (free distance - true depth),
   (mesh depth - true depth) and (free distance - mesh depth), along the ray (world units).
3. Any scene: over every ``--every``-th training view, the share of the covered rays (the true mesh
   hit) whose stretch end (free distance - margin) lies behind the true first surface by more than
   0, 0.02 and 0.05, and by more than 0.02 per object of the scene's ``parts/*.ply`` (each true hit
   assigned to its nearest part): where the stage's field put its density behind a surface.
4. ``--rules`` (a run made with ``free_space.save_levels=[...]``; a stage-only run is enough:
   ``iters=1 gif_frames=0``): other rules for where the stretches end, over all training views
   (bench/free_space_end_rules.py).
A diagnosis aid for the development scenes; it chooses nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing
sys.path.insert(0, str(REPO / "bench"))

from surface_by_part import nearest_part  # noqa: E402  (bench/ is not a package)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--scene", type=Path, default=REPO / "outputs" / ".cache" / "bench_scenes" / "ground")
    ap.add_argument("--points", type=int, default=400000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--every", type=int, default=5, help="part 3: every this many training views")
    ap.add_argument("--rules", action="store_true", help="part 4: other stretch-end rules (needs save_levels)")
    args = ap.parse_args()
    from volsdf_run import load_sdf_field
    from l3d_app.geometry.mesh_io import load_mesh
    from l3d_app.geometry.rays import camera_rays
    from l3d_app.render.sdf.densities import laplace_cdf
    from l3d_app.render.volume.free_space import FreeRays
    from l3d_app.render.mesh.rgbd import true_depth_maps

    torch.set_num_threads(args.threads)
    conf, data, model = load_sdf_field(args.run, args.scene, ("free_space.pt", "mesh.ply"))
    box = data.scene_box.tolist()
    cams = data.cameras[data.train]
    origins, dirs = camera_rays(cams, normalize=False)                      # (V, H, W, 3), camera z = 1
    norm = dirs.norm(dim=-1)
    saved = torch.load(args.run / "free_space.pt", weights_only=True)
    flat_o, flat_d = origins.reshape(-1, 3), (dirs / norm[..., None]).reshape(-1, 3)
    free = FreeRays.from_distances(flat_o[saved["index"]], flat_d[saved["index"]], saved["distance"].float(), box,
                                   float(conf.free_space.margin))
    beta = 0.005
    gen = torch.Generator().manual_seed(0)
    pts, length = free.sample(args.points, gen, float(conf.free_space.margin_beta) * beta)
    with torch.no_grad():
        f = torch.cat([model.sdf(p) for p in pts.split(50000)])
    g = laplace_cdf(-f, beta) * length
    near = f < 0.02
    print(f"loss points {len(f)}: f < 0 {float((f < 0).float().mean()):.4f}, f < 0.02 {float(near.float().mean()):.4f}, "
          f"their share of the integrand {float(g[near].sum() / g.sum()):.3f}")
    stretch_ends_behind(args, conf, data, cams, saved, load_mesh, true_depth_maps, camera_rays)
    if args.rules:
        end_rules(args, conf, data, cams, saved, flat_o, flat_d, norm)
    if args.scene.name != "ground":
        return
    truth = true_depth_maps(load_mesh(str(args.scene / "mesh.ply")), cams, scale=1) * norm
    mesh = true_depth_maps(load_mesh(str(args.run / "mesh.ply")), cams, scale=1) * norm
    hit = origins + dirs / norm[..., None] * torch.nan_to_num(truth, posinf=0.0)[..., None]
    dist = torch.full((truth.numel(),), float("nan"))
    dist[saved["index"]] = saved["distance"].float()
    dist = dist.reshape(truth.shape)
    l1 = (hit[..., 0] + 0.45).abs() + (hit[..., 1] - 0.4).abs()         # the tray: a square about (-0.45, 0.4)
    seen = torch.isfinite(truth)
    floor = tray_floor(args.scene, origins, dirs / norm[..., None], truth)
    for name, m in (("tray floor", floor), ("tray rim/walls", seen & (l1 < 0.43) & ~floor), ("elsewhere", seen & (l1 >= 0.43))):
        ok = m & torch.isfinite(dist) & torch.isfinite(mesh)
        print(f"{name}: rays {int(m.sum())}; median free - truth {float((dist - truth)[ok].median()):+.3f}, "
              f"mesh - truth {float((mesh - truth)[ok].median()):+.3f}, free - mesh {float((dist - mesh)[ok].median()):+.3f}")


def tray_floor(scene: Path, origins: torch.Tensor, dirs: torch.Tensor, truth: torch.Tensor):
    """(N,) bool: the rays whose true first hit is ground's tray floor (a square about (-0.45, 0.4)
    below z = -0.3); None on other scenes. ``truth``: (N,) distance along unit ``dirs``."""
    if scene.name != "ground":
        return None
    hit = origins + dirs * torch.nan_to_num(truth, posinf=0.0)[..., None]
    l1 = (hit[..., 0] + 0.45).abs() + (hit[..., 1] - 0.4).abs()
    return torch.isfinite(truth) & (l1 < 0.35) & (hit[..., 2] < -0.3)


def end_rules(args, conf, data, cams, saved, flat_o, flat_d, norm) -> None:
    """Part 4 of the module docstring: printed, nothing returned."""
    from free_space_end_rules import report_end_rules
    from l3d_app.geometry.mesh_io import load_mesh
    from l3d_app.render.mesh.rgbd import true_depth_maps

    if "levels" not in saved:
        raise SystemExit(f"{args.run}: free_space.pt has no other levels (run with free_space.save_levels=[...])")
    truth = (true_depth_maps(load_mesh(str(args.scene / "mesh.ply")), cams, scale=1) * norm).reshape(-1)
    seen = torch.isfinite(truth)
    part = torch.full(truth.shape, -1, dtype=torch.long)
    parts = sorted((args.scene / "parts").glob("*.ply"))
    if parts:
        part[seen] = nearest_part(flat_o[seen] + flat_d[seen] * truth[seen, None], [load_mesh(str(q)) for q in parts])
    print(f"end rules (all {len(cams)} training views, {int(seen.sum())} covered rays):")
    report_end_rules(cams, data.images[data.train], saved, float(conf.free_space.margin),
                     float(conf.free_space.opacity), truth, part, tray_floor(args.scene, flat_o, flat_d, truth),
                     flat_o, flat_d)


def stretch_ends_behind(args, conf, data, cams, saved, load_mesh, true_depth_maps, camera_rays) -> None:
    """Part 3 of the module docstring: printed, nothing returned."""
    views = torch.arange(0, len(cams), args.every)
    hw = cams.height * cams.width
    origins, dirs = camera_rays(cams[views], normalize=False)
    norm = dirs.norm(dim=-1).reshape(-1)
    truth = (true_depth_maps(load_mesh(str(args.scene / "mesh.ply")), cams[views], scale=1).reshape(-1) * norm)
    dist = torch.full((len(cams) * hw,), float("nan"))
    dist[saved["index"]] = saved["distance"].float()
    end = dist[(views[:, None] * hw + torch.arange(hw)[None]).reshape(-1)] - float(conf.free_space.margin)
    seen = torch.isfinite(truth)
    print(f"stretch ends (every {args.every}th training view, {int(seen.sum())} covered rays): behind the truth by "
          + ", ".join(f"> {tol}: {float((seen & (end > truth + tol)).sum() / seen.sum()):.4f}" for tol in (0.0, 0.02, 0.05)))
    parts = sorted((args.scene / "parts").glob("*.ply"))
    if not parts:
        return
    hit = (origins.reshape(-1, 3) + dirs.reshape(-1, 3) / norm[:, None] * torch.nan_to_num(truth, posinf=0.0)[:, None])[seen]
    part = nearest_part(hit, [load_mesh(str(q)) for q in parts])
    behind = (end > truth + 0.02)[seen]
    print("  by > 0.02, per object: " + ", ".join(f"{p.stem} {float(behind[part == k].float().mean()):.3f} "
                                                   f"({int((part == k).sum())} rays)" for k, p in enumerate(parts)))


if __name__ == "__main__":
    main()
