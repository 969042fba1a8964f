"""The registry of diffusion priors: ``conf/prior/<name>.yaml`` names an entry here.

``PRIORS.build(cfg.prior, device=ctx.device)`` returns a frozen
:class:`~l3d_app.diffusion.prior.DiffusionPrior` (``builtin`` is registered by
:mod:`l3d_app.diffusion.builtin_prior`; adapters for other priors register themselves the
same way; :mod:`l3d_app.diffusion` imports them).
"""

from __future__ import annotations

from l3d_app.registry import Registry

PRIORS = Registry("diffusion prior")
