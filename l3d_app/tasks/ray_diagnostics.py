"""ray_diagnostics: the pixel grid, the ray directions and the sample points of one camera.

The pictures of the course's first volume-rendering part, written before anything is
trained (:mod:`l3d_app.render.volume.diagnostics`): ``pixel_grid.png`` (normalised pixel
coordinates as red/green), ``ray_directions.png`` (``|d|`` of the unit world-space ray
directions as RGB), ``sample_points.png`` (the points ``o + t d`` of ``n_samples`` evenly
spaced samples in ``[near, far]`` on every ``stride``-th pixel's ray, coloured by ``t``,
seen by an observer camera beside the frustum) and ``sample_points_camera.png`` (the same
points seen by the camera itself). metrics.json holds checks against closed forms: the
largest ``| |d| - 1 |`` and the angle of the corner pixel's ray to the optical axis, measured
and analytic (``atan(sqrt(((W-1)/2)^2 + ((H-1)/2)^2) / f)`` for a centred principal point).
"""

from __future__ import annotations

import math

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.rays import camera_rays
from l3d_app.registry import RENDERERS, TASKS
from l3d_app.render.volume.diagnostics import depth_colormap, pixel_grid_image, ray_direction_image, ray_sample_points
from l3d_app.runtime.media import save_png
from l3d_app.tasks.common import require_positive


@TASKS.register("ray_diagnostics")
def ray_diagnostics(cfg, ctx) -> dict:
    """Write the three diagnostic pictures of the camera; return the closed-form checks."""
    require_positive(cfg, "image_size", "distance", "fov", "far", "n_samples", "stride")
    if not 0 <= float(cfg.near) < float(cfg.far):
        raise UserError(f"need 0 <= near < far, got near={cfg.near}, far={cfg.far}")
    size = int(cfg.image_size)
    cams = look_at_cameras(float(cfg.distance), float(cfg.elevation), float(cfg.azimuth), float(cfg.fov),
                           size, device=ctx.device)
    grid = pixel_grid_image(size, size)
    dirs_img = ray_direction_image(cams)[0].cpu()
    points, t = ray_sample_points(cams, float(cfg.near), float(cfg.far), int(cfg.n_samples), int(cfg.stride))
    colors = depth_colormap(t, vmax=float(cfg.far))                   # (N, 3) by t / far
    observer = look_at_cameras(float(cfg.observer.distance), float(cfg.observer.elevation),
                               float(cfg.observer.azimuth), float(cfg.fov), size, device=ctx.device)
    renderer = RENDERERS.build(cfg.point_renderer)
    cloud = PointCloud(points, colors.to(points.device))
    with torch.no_grad():
        side = renderer(cloud, observer)["image"][0].cpu()
        own = renderer(cloud, cams)["image"][0].cpu()
    for name, image in (("pixel_grid", grid), ("ray_directions", dirs_img), ("sample_points", side),
                        ("sample_points_camera", own)):
        save_png(ctx.path(f"{name}.png"), image)
        ctx.logger.image(f"ray_diagnostics/{name}", image, 0)
    _, dirs = camera_rays(cams, normalize=True)                     # (1, H, W, 3)
    forward = cams.R[0, 2]
    corner = torch.rad2deg(torch.acos((dirs[0, 0, 0] @ forward).clamp(-1, 1)))
    half = (size - 1) / 2.0
    analytic = math.degrees(math.atan(math.hypot(half, half) / float(cams.fx[0])))
    return {
        "image_size": size,
        "max_dir_norm_error": float((dirs.norm(dim=-1) - 1).abs().max()),
        "corner_ray_angle_deg": round(float(corner), 5),
        "corner_ray_angle_deg_analytic": round(analytic, 5),
        "n_sample_points": int(points.shape[0]),
        "sample_t_min": float(t.min()),
        "sample_t_max": float(t.max()),
    }
