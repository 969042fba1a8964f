"""Diffusion priors behind one interface, and what score distillation needs from them.
Heavy optional libraries (diffusers, transformers) are imported only when a Stable
Diffusion prior is built."""

from l3d_app.exports import lazy_exports

# Registering modules: importing the package completes its registries.
from l3d_app.diffusion import builtin_prior, stable_diffusion  # noqa: F401,E402

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "PRIORS": "registry",
    "DiffusionPrior": "prior",
    "BuiltinPrior": "builtin_prior",
    "ddim_sample": "sampling",
    "ViewPrompts": "view_prompts",
})
