"""Stages: a method's work before and around its training loop (:mod:`~l3d_app.stages.base`)."""

from l3d_app.exports import lazy_exports

# Registering modules: importing the package completes its registries.
from l3d_app.stages import coarse_to_fine, free_space, sphere_init  # noqa: F401,E402

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "Stage": "base",
    "Stages": "base",
    "MethodState": "base",
})
