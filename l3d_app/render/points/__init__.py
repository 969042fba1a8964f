"""Point-cloud renderers: z-buffered disc splats and the pseudo-renderer."""

from l3d_app.render.points import renderer  # noqa: F401  (RENDERERS)
