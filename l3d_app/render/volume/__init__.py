"""Volume rendering along rays: compositing, samplers and estimators, occupancy grids, known free space."""

from l3d_app.render.volume import renderer, estimators  # noqa: F401  (RENDERERS, SAMPLERS)
