"""Pieces shared by the prior tasks (train_prior, sds_image, sds_mesh, sds_nerf): the configured prior."""

from __future__ import annotations

from l3d_app.diffusion.registry import PRIORS


def load_prior(cfg, device):
    """The configured prior (``prior=builtin`` | ``prior=stable_diffusion prior.path=DIR``), frozen."""
    return PRIORS.build(cfg.prior, device=device)
