"""Signed distance fields: SDF-to-density conversions (VolSDF, NeuS), SDF volume rendering, sphere tracing."""

from l3d_app.render.sdf import densities, neus, neus_logistic  # noqa: F401  (DENSITIES)
