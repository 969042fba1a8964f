"""neural_sdf: fit a neural SDF to a point cloud (surface samples, no normals).

``python main.py task=neural_sdf`` (built-in: points on a torus) or
``data=bunny data.path=../shared/data/bunny/bunny_pointcloud.npz``.

Model: :class:`~l3d_app.models.sdf_net.SDFNetwork` (harmonic encoding, Softplus MLP, no output
activation, geometric init to a sphere). Loss per step, on ``batch_points`` cloud points
``P`` and as many uniform points ``Q`` in the padded bounds of the cloud:

    mean |f(P)|                                  the surface is the zero level set
  + w_eikonal  * mean (|grad f(P u Q)| - 1)^2    a distance field (safe norm: finite at kinks)
  + w_offsurface * mean exp(-offsurface_scale |f(Q)|)   no spurious zeros away from the points

Outputs: ``mesh.<ply|obj>`` (marching cubes of f = 0), ``mesh.gif`` (360 sphere-traced shading of
the SDF), ``metrics.json`` with ``chamfer`` (symmetric mean of non-squared nearest distances
between mesh samples and the cloud, world units), ``f1`` at ``f1_threshold``, ``seconds``.
"""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.marching_cubes import sdf_to_mesh
from l3d_app.geometry.mesh_io import save_mesh
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.rays import camera_rays
from l3d_app.geometry.sampling import sample_surface
from l3d_app.losses.eikonal import eikonal_loss
from l3d_app.metrics.chamfer import chamfer_distance
from l3d_app.metrics.fscore import fscore
from l3d_app.models.sdf_net import SDFNetwork
from l3d_app.registry import DATASETS, TASKS
from l3d_app.render.previews import frames_within_budget
from l3d_app.render.sdf.sphere_tracing import render_sdf_shaded
from l3d_app.render.turntable import orbit_cameras
from l3d_app.render.volume.renderer import render_rays_chunked
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.media import save_gif
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.random import rand, randint, randperm
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec, require_mesh_formats, require_mesh_resolution, require_nonnegative, require_positive


@TASKS.register("neural_sdf")
def neural_sdf(cfg, ctx) -> dict:
    require_positive(cfg, "iters", "batch_points", "lr", "offsurface_scale", "init_radius", "eval_every",
                     "eval_points", "f1_threshold")
    require_nonnegative(cfg, "w_eikonal", "w_offsurface", "bounds_padding")
    require_mesh_resolution(cfg)
    require_mesh_formats(cfg, "mesh_format", ("ply", "obj"))
    if not 0.0 <= float(cfg.val_fraction) < 1.0:
        raise UserError(f"val_fraction must be in [0, 1), got {cfg.val_fraction!r}")
    cloud = DATASETS.build(cfg.data)
    points = cloud.points if isinstance(cloud, PointCloud) else torch.as_tensor(cloud)
    points = points.float().to(ctx.device)
    if points.shape[0] < 2:
        raise UserError(f"neural_sdf needs a point cloud of at least 2 points, got {points.shape[0]}")
    lo, hi = points.min(0).values, points.max(0).values
    if not float((hi - lo).max()) > 0:
        raise UserError("neural_sdf needs a point cloud with extent: all its points coincide")
    pad = float(cfg.bounds_padding) * float((hi - lo).max())
    lo, hi = lo - pad, hi + pad
    box = (lo.tolist(), hi.tolist())
    radius = float(cfg.init_radius) * 0.5 * float((hi - lo).min())
    net = SDFNetwork(radius=radius, **dict(cfg.model)).to(ctx.device)
    opt, scheds = build_optimizer(cfg.optim, net.parameters(), int(cfg.iters))
    trainable = Trainable({"sdf": net}, opt, schedulers=scheds)
    # a seeded validation fraction of the cloud: never trained on, read by the periodic evaluation
    n_val = int(round(float(cfg.val_fraction) * points.shape[0]))
    perm = randperm(points.shape[0], ctx.generator, ctx.device)
    val_points, train_points = points[perm[:n_val]], points[perm[n_val:]]
    if (float(cfg.val_fraction) > 0 and n_val == 0) or n_val == points.shape[0]:
        raise UserError(f"val_fraction={cfg.val_fraction} of {points.shape[0]} points holds out {n_val}: "
                        f"both the training and the validation points must be non-empty (val_fraction=0: no validation)")
    n = int(cfg.batch_points)
    centre = 0.5 * (lo + hi)

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        idx = randint(0, train_points.shape[0], (n,), ctx.generator, ctx.device)
        q = lo + rand((n, 3), ctx.generator, ctx.device) * (hi - lo)
        x = torch.cat([train_points[idx], q]).requires_grad_(True)
        f = net(x)[0]
        (grad,) = torch.autograd.grad(f.sum(), x, create_graph=True)
        surf = f[:n].abs().mean()
        eik = eikonal_loss(grad)
        off = torch.exp(-float(cfg.offsurface_scale) * f[n:].abs()).mean()
        loss = surf + float(cfg.w_eikonal) * eik + float(cfg.w_offsurface) * off
        return {"loss": loss, "surface": surf.detach(), "eikonal": eik.detach(), "offsurface": off.detach()}

    def eval_fn(step: int) -> Dict[str, float]:     # mean |f| at held-out cloud points (world units)
        return {"surface_abs": float(net(val_points)[0].abs().mean())}

    with ctx.stopwatch.stage("train"):
        budget = TimeBudget.of(ctx).keep_renders(int(cfg.mesh_resolution) ** 3, n_val)   # the mesh: the grid's points
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "neural_sdf"), eval_fn if n_val else None, budget)
    metrics: Dict[str, float] = {"iters": result.step, "n_params": sum(p.numel() for p in net.parameters()),
                                 "n_points": int(points.shape[0]),
                                 "val_surface_abs": (round(result.metrics["surface_abs"], 6)          # None: no validation
                                                     if "surface_abs" in result.metrics else None),
                                 "history": result.history_rows()}
    sdf = net.sdf
    fmt = str(cfg.mesh_format).lower().lstrip(".")
    try:
        mesh = sdf_to_mesh(sdf, resolution=int(cfg.mesh_resolution), bounds=box, device=ctx.device)
    except UserError as err:
        print(f"l3d_app: warning: no mesh written: {err}", flush=True)
        return {**metrics, "mesh_faces": 0}
    save_mesh(mesh, ctx.path(f"mesh.{fmt}"))
    metrics["mesh_faces"] = int(mesh.num_faces)
    with torch.no_grad():
        pred = sample_surface(mesh.to("cpu"), int(cfg.eval_points), generator=torch.Generator().manual_seed(2)).points
        ref = points.cpu()
        metrics["chamfer"] = round(float(chamfer_distance(pred, ref, squared=False)), 6)
        metrics["f1"] = round(fscore(pred, ref, float(cfg.f1_threshold))["f1"], 4)
    if int(cfg.gif_frames) > 0:
        ext = float((hi - lo).norm())
        cams = orbit_cameras(int(cfg.gif_frames), 1.6 * ext, float(cfg.gif_elevation), 45.0, int(cfg.turntable_size),
                             up=getattr(cloud, "up", None), at=centre.tolist(), device=ctx.device)  # +Y unless known

        def render(c):
            o, d = camera_rays(c, normalize=True)
            return render_rays_chunked(lambda a, b: {"rgb": render_sdf_shaded(sdf, a, b, box)}, o, d, 8192)["rgb"]

        frames = frames_within_budget(budget, cams, render, "mesh_gif/budget")     # under a budget: what fits
        if frames is not None:
            save_gif(ctx.path("mesh.gif"), frames, fps=float(cfg.fps))
    return metrics
