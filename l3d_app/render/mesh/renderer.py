"""MeshRenderer: hard rasteriser + Phong/Lambert/flat/unlit shading, with optional SSAA.

Registered as ``renderer=mesh``. Only covered pixels are shaded (packed fragments).
"""

from __future__ import annotations

import time
from typing import Dict, Optional, Sequence

import torch
import torch.nn.functional as F

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.registry import RENDERERS
from l3d_app.render.mesh.rasterize import project_vertices, rasterize_projected
from l3d_app.render.mesh.shading import Lights, Material, interpolate_vertices, normalize, phong
from l3d_app.runtime.config_values import config_floats, config_rows
from l3d_app.geometry.textures import sample_texture_t

SHADINGS = ("phong", "lambert", "flat", "unlit")
DEFAULT_ALBEDO = (0.85, 0.85, 0.85)  # grey-white for meshes without colours or texture


class _StageTimer:
    """Wall-clock seconds per stage (synchronising CUDA when enabled)."""

    def __init__(self, enabled: bool, device: torch.device):
        self.enabled, self.device, self.times = enabled, device, {}
        self._t = self._now() if enabled else 0.0

    def _now(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    def lap(self, name: str) -> None:
        if self.enabled:
            now = self._now()
            self.times[name] = now - self._t
            self._t = now


def scale_cameras(cams: Cameras, factor: int) -> Cameras:
    """The same cameras at ``factor`` times the resolution (for supersampling)."""
    s = float(factor)
    return Cameras(cams.R, cams.t, cams.fx * s, cams.fy * s, cams.cx * s, cams.cy * s,
                   cams.width * factor, cams.height * factor)


@RENDERERS.register("mesh")
class MeshRenderer:
    """Render a :class:`Mesh` from B cameras.

    Args:
        shading: 'phong' (smooth normals + specular), 'lambert' (smooth normals, no
            specular), 'flat' (face normals + specular), 'unlit' (albedo only).
        background: RGB of uncovered pixels.
        ambient, diffuse, specular: material coefficients (scalar or RGB) of the
            :class:`~l3d_app.render.mesh.shading.Material`; the ambient light is white.
        shininess: Phong exponent.
        light_direction: world direction FROM the surface TOWARDS a directional light; None
            (default) = a headlight, i.e. a directional light towards each camera.
        light_color: RGB of that directional light (also of the point lights).
        point_lights: list of world positions [x, y, z] of extra point lights.
        antialias: supersampling factor s (1 = off): render at s*H x s*W, average-pool.
        near: camera-depth near plane; faces with a vertex closer are dropped.
        cull_backfaces: drop faces pointing away from the camera.
    """

    def __init__(self, shading: str = "phong", background: Sequence[float] = (1.0, 1.0, 1.0),
                 ambient=0.4, diffuse=0.6, specular=0.2, shininess: float = 32.0,
                 light_direction: Optional[Sequence[float]] = None,
                 light_color: Sequence[float] = (1.0, 1.0, 1.0),
                 point_lights: Sequence[Sequence[float]] = (), antialias: int = 1,
                 near: float = 1e-3, cull_backfaces: bool = False):
        if shading not in SHADINGS:
            raise UserError(f"unknown shading '{shading}'; known: {', '.join(SHADINGS)}")
        if int(antialias) < 1:
            raise UserError(f"antialias must be an integer >= 1, got {antialias}")
        if len(background) != 3:
            raise UserError(f"background must be 3 numbers (RGB), got {background}")
        for name, value in (("ambient", ambient), ("diffuse", diffuse), ("specular", specular),
                            ("light_color", light_color)):
            _require_nonnegative_color(name, value)
        if not float(shininess) > 0:
            raise UserError(f"shininess must be > 0 (a Phong exponent), got {shininess}")
        self.shading, self.background = shading, tuple(float(c) for c in background)
        self.material = Material(ambient, diffuse, specular, float(shininess))
        self.light_direction = (None if light_direction is None
                                else tuple(config_floats(light_direction, "light_direction", 3)))
        self.light_color = tuple(float(c) for c in light_color)
        self.point_lights = [tuple(p) for p in config_rows(point_lights or [], "point_lights", None, 3,
                                                           "a list of [x, y, z] positions")]
        self.antialias, self.near = int(antialias), float(near)
        self.cull_backfaces = bool(cull_backfaces)

    # ------------------------------------------------------------------ API
    def __call__(self, mesh: Mesh, cams: Cameras, return_timings: bool = False
                 ) -> Dict[str, torch.Tensor]:
        """Render; returns a dict of (B, H, W, ...) tensors on the mesh's device:

        image (B, H, W, 3) in [0, 1]; alpha (B, H, W) coverage in [0, 1]; depth (B, H, W)
        camera Z (0 on background; with SSAA the mean over covered subsamples); normals
        (B, H, W, 3) unit world normals (0 on background); pix_to_face (B, H, W) long (-1
        on background; with SSAA the face at the central subsample). With
        ``return_timings`` also ``timings``: seconds of 'transform', 'rasterize', 'shade'.
        """
        timer = _StageTimer(return_timings, mesh.device)
        s = self.antialias
        rcams = scale_cameras(cams, s) if s > 1 else cams
        B, H, W = rcams.batch_size, rcams.height, rcams.width
        uv, z = project_vertices(rcams, mesh.verts, self.near)
        flat = self.shading == "flat"
        normals_src = mesh.face_normals() if flat else mesh.vertex_normals()  # (F|V, 3)
        timer.lap("transform")
        frags = rasterize_projected(uv, z, mesh.faces, H, W, near=self.near,
                                    cull_backfaces=self.cull_backfaces)
        timer.lap("rasterize")
        out = self._shade(mesh, rcams, frags, normals_src, flat, B, H, W)
        if s > 1:
            out = _downsample(out, s)
        timer.lap("shade")
        if return_timings:
            out["timings"] = dict(timer.times)
        return out

    # ------------------------------------------------------------ internals
    def lights(self, per_view_dir: torch.Tensor) -> Lights:
        """The lights, given the headlight direction(s) (3, P) or (3, 1) of the points."""
        direction = per_view_dir if self.light_direction is None else self.light_direction
        lights = Lights(ambient=(1.0, 1.0, 1.0), directional=[(direction, self.light_color)])
        lights.point = [(p, self.light_color) for p in self.point_lights]
        return lights

    def albedo(self, mesh: Mesh, faces: torch.Tensor, corners, bary_t: torch.Tensor
               ) -> torch.Tensor:
        """(3, P) (or (3, 1) constant) base colour of packed fragments: UV texture, vertex
        colours, or grey-white. ``faces`` (P,) face ids, ``corners`` their 3 vertex ids."""
        if mesh.has_texture:
            uv_corners = [mesh.faces_uvs[:, k].index_select(0, faces) for k in range(3)]
            uv = interpolate_vertices(mesh.verts_uvs.t().to(bary_t.dtype), uv_corners, bary_t)
            return sample_texture_t(mesh.texture, uv).to(bary_t.dtype)
        if mesh.vert_colors is not None:
            return interpolate_vertices(mesh.vert_colors.t().to(bary_t.dtype), corners, bary_t)
        return bary_t.new_tensor(DEFAULT_ALBEDO)[:, None]

    def _shade(self, mesh, cams, frags, normals_src, flat, B, H, W):
        f, pix, bary_t = frags.fg_faces, frags.fg_pixels, frags.fg_bary_t
        dt = bary_t.dtype
        corners = [mesh.faces[:, k].index_select(0, f) for k in range(3)]
        if flat:
            normals = normals_src.t().to(dt).index_select(1, f)
        else:
            normals = normalize(interpolate_vertices(normals_src.t().to(dt), corners, bary_t))
        albedo = self.albedo(mesh, f, corners, bary_t)
        if self.shading == "unlit":
            rgb = albedo.expand(3, f.shape[0])
        else:
            points = interpolate_vertices(mesh.verts.t().to(dt), corners, bary_t)
            eye, head = cams.centers().t(), -cams.R[:, 2].t()  # (3, B) each
            if B > 1:
                view = torch.div(pix, H * W, rounding_mode="floor")
                eye, head = eye.index_select(1, view), head.index_select(1, view)
            rgb = phong(points, normals, albedo, eye, self.lights(head), self.material,
                        specular=self.shading != "lambert")
        n = B * H * W
        bg = self.background
        image = (torch.full((n, 3), bg[0], dtype=dt, device=f.device) if bg[0] == bg[1] == bg[2]
                 else torch.tensor(bg, dtype=dt, device=f.device).expand(n, 3).contiguous())
        image.index_copy_(0, pix, rgb.clamp(0, 1).t())
        nimg = torch.zeros(n, 3, dtype=dt, device=f.device).index_copy_(0, pix, normals.t())
        return {"image": image.view(B, H, W, 3), "alpha": frags.mask.to(dt),
                "depth": frags.zbuf, "normals": nimg.view(B, H, W, 3),
                "pix_to_face": frags.pix_to_face}


def _downsample(out: Dict[str, torch.Tensor], s: int) -> Dict[str, torch.Tensor]:
    """Average-pool supersampled outputs by ``s`` (see ``MeshRenderer.__call__``)."""
    pool = lambda x: F.avg_pool2d(x.permute(0, 3, 1, 2), s).permute(0, 2, 3, 1)  # noqa: E731
    alpha = pool(out["alpha"][..., None])
    depth_sum = pool(out["depth"][..., None])
    depth = torch.where(alpha > 0, depth_sum / alpha.clamp_min(1e-12), 0.0)
    normals = F.normalize(pool(out["normals"]), dim=-1, eps=1e-12)
    return {"image": pool(out["image"]), "alpha": alpha[..., 0], "depth": depth[..., 0],
            "normals": normals, "pix_to_face": out["pix_to_face"][:, s // 2::s, s // 2::s]}


def _require_nonnegative_color(name: str, value) -> None:
    """UserError unless ``value`` is a number >= 0 or 3 of them (a reflectance or light colour)."""
    try:
        values = [float(value)]
    except (TypeError, ValueError):
        try:
            values = [float(v) for v in value]
        except (TypeError, ValueError):
            values = []
    if len(values) not in (1, 3) or not all(v >= 0 for v in values):
        raise UserError(f"{name} must be a number >= 0 or 3 of them (RGB), got {value}")
