"""What a surface method writes after training: its SDF's zero level set as a coloured mesh scored against the
true surface, and the frames of its turntables."""

from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence, Tuple

from l3d_app.geometry.cameras import Cameras

import torch

from l3d_app.geometry.mesh import Mesh
from l3d_app.metrics.surface_scores import surface_scores
from l3d_app.render.evaluation import render_views
from l3d_app.render.field_mesh import ColorFn, extract_mesh, save_field_mesh
from l3d_app.render.mesh.rgbd import true_depth_maps
from l3d_app.render.sdf.sphere_tracing import render_sdf_shaded
from l3d_app.render.turntable import color_depth_frames


@torch.no_grad()
def surface_mesh(sdf: Callable[[torch.Tensor], torch.Tensor], color_fn: ColorFn, box, data, resolution: int,
                 formats: Sequence[str], path: Callable[[str], object], logger, device=None,
                 cull: Optional[Callable[[Mesh], Tuple[Mesh, float]]] = None, n_points: int = 10000
                 ) -> Dict[str, float]:
    """Marching cubes of ``sdf`` ((N, 3) -> (N,)) over ``box`` at ``resolution`` cells per axis, vertex colours
    from ``color_fn(points, outward normals)``, saved as ``path("mesh")`` in ``formats``; scored with
    :func:`~l3d_app.metrics.surface_scores.surface_scores` (``n_points`` samples of each surface, F1 at 0.05
    world units, the ``*_observed`` figures on what the training views see) when ``data`` carries its true
    surface (``data.mesh``). ``cull(mesh) -> (mesh, share of area removed)`` first drops what no training camera
    sees (the whole level set then in ``mesh_uncut.ply``). Returns the figures (``mesh_faces`` 0: no level set)."""
    mesh = extract_mesh(sdf, box, int(resolution), 0.0, color_fn=color_fn, device=device)
    if mesh is None:      # empty level set: say so, keep the other results
        logger.text("mesh", "no mesh written: the SDF has no zero level set in the box")
        return {"mesh_faces": 0}
    out: Dict[str, float] = {}
    if cull is not None:              # what no training camera sees: free space, not a leftover
        save_field_mesh(mesh, path("mesh_uncut"), ["ply"])
        mesh, out["mesh_culled_area"] = cull(mesh)
    save_field_mesh(mesh, path("mesh"), formats)
    out["mesh_faces"] = int(mesh.num_faces)
    truth = getattr(data, "mesh", None)  # the built-in scene's; data=blender data.mesh_path=FILE loads one
    if truth is not None:
        cams = data.cameras[data.train.to(data.cameras.device)].to("cpu")
        depth = true_depth_maps(truth.to("cpu"), cams, scale=4)       # what the training views see of the truth
        scores = surface_scores(mesh, truth, cameras=cams, depth_maps=depth, n=int(n_points), threshold=0.05, seed=2)
        out.update({k: round(v, 6) for k, v in scores.items()})
    return out


def surface_turntables(sdf: Callable[[torch.Tensor], torch.Tensor], render, box, chunk: int
                       ) -> Dict[str, Callable[[Cameras], torch.Tensor]]:
    """The frame functions (cameras -> (N, H, W, 3)) of ``render.gif`` (the volume render ``render(origins, dirs)``:
    colour | depth) and ``geometry.gif`` (sphere-traced shading of ``sdf`` in ``box``), ``chunk`` rays per call."""
    shade = lambda o, d: {"color": render_sdf_shaded(sdf, o, d, box)}  # noqa: E731
    return {"render.gif": color_depth_frames(render, int(chunk)),
            "geometry.gif": lambda cams: render_views(shade, cams, int(chunk))["color"]}
