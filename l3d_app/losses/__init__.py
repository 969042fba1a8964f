"""Losses: a method's loss terms (terms.py), eikonal, free space, patch consistency, mesh regularisers, NeRF
regularisers, occupancy BCE, score distillation."""

from l3d_app.exports import lazy_exports

# Registering modules: importing the package completes its registries.
from l3d_app.losses import (occupancy, mesh_regularizers, render_terms, eikonal, free_space,  # noqa: F401,E402
                            patch_consistency)

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "eikonal_loss": "eikonal",
    "LossTerm": "terms",
    "LossTerms": "terms",
    "laplacian_smoothing": "mesh_regularizers",
    "normal_consistency": "mesh_regularizers",
    "edge_length": "mesh_regularizers",
    "bce_with_logits": "occupancy",
    "sds_loss": "sds",
})
