"""Mesh renderers: hard and soft rasterisation, shading, visibility culling, RGB-D views."""

from l3d_app.render.mesh import renderer, soft_rasterize  # noqa: F401  (RENDERERS)
