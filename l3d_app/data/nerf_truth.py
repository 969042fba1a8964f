"""Ground truth of the built-in NeRF scene, for scoring reconstructed surfaces.

The built-in multi-view dataset (:func:`l3d_app.data.nerf_views.nerf_builtin`) is rendered from
the mesh :func:`~l3d_app.data.nerf_views.nerf_scene`; this module exposes that surface as
area-uniform point samples (the reference of chamfer / F-score figures) and its bounds.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from l3d_app.data.nerf_views import nerf_scene
from l3d_app.geometry.sampling import sample_surface


def builtin_surface_points(num_samples: int = 20000, generator: Optional[torch.Generator] = None,
                           device=None) -> torch.Tensor:
    """(num_samples, 3) points uniform per unit area on the built-in scene's surface (world
    units); seeded by ``generator`` (a CPU generator; default: seed 0)."""
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    pts = sample_surface(nerf_scene(), int(num_samples), generator=gen).points
    return pts.detach().to(device=device)


def builtin_surface_bounds() -> Tuple[torch.Tensor, torch.Tensor]:
    """(lo (3,), hi (3,)) axis-aligned bounds of the built-in scene's mesh (world units)."""
    v = nerf_scene().verts
    return v.min(dim=0).values, v.max(dim=0).values
