"""Signed distance fields: SDF-to-density conversions (VolSDF, NeuS), SDF volume rendering, sphere tracing."""

from l3d_app.render.sdf import densities, neus  # noqa: F401  (DENSITIES)
