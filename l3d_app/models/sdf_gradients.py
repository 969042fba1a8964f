"""A field callable that also returns the spatial SDF gradient (exact when the model has it)."""

from __future__ import annotations

import torch



def field_with_gradient(model):
    """``fn(points (N, 3), dirs (N, 3)) -> (sdf (N,), rgb (N, 3), grad f (N, 3))``: the model's
    exact gradient when it has one (:class:`~l3d_app.models.sdf_grid.SDFGridField`), else
    autograd (graph kept while training; without grad mode only (sdf, rgb))."""
    if hasattr(model, "sdf_rgb_grad"):
        return model.sdf_rgb_grad

    def fn(points: torch.Tensor, dirs: torch.Tensor):
        if not torch.is_grad_enabled():
            return model(points, dirs)
        p = points.detach().requires_grad_(True)
        f, rgb = model(p, dirs)
        (g,) = torch.autograd.grad(f.sum(), p, create_graph=True)
        return f, rgb, g

    return fn
