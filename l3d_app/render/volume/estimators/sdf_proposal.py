"""SDF-cache proposal: a trilinear copy of the SDF places a few field samples at the surface."""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.registry import SAMPLERS
from l3d_app.render.sdf.densities import transition_width
from l3d_app.render.volume.estimators.base import Box, Estimator, Samples, segment_ends
from l3d_app.render.volume.estimators.zero_crossing import first_crossing, refine_crossing
from l3d_app.render.volume.rendering import pack_samples
from l3d_app.render.sdf.cache import SDFGridCache
from l3d_app.render.volume.samplers import sample_pdf, stratified_samples
from l3d_app.render.volume.renderer import composite
from l3d_app.runtime.config_values import config_floats
from l3d_app.runtime.random import rand


@SAMPLERS.register("sdf_cache")
class SDFCacheProposal(Estimator):
    """Coarse pass on a cached SDF, fine samples near its zero level set (VolSDF / NeuS).

    1. ``n_coarse`` stratified look-ups per ray of an :class:`SDFGridCache` (``resolution``^3
       trilinear copy of ``field.sdf``, refreshed every ``every`` steps by :meth:`update`; with
       ``resolution`` 0 the field's own SDF is evaluated, no grad);
    2. their weights under the run's density (``sampling(..., density=...)``, a ``DENSITIES``
       module, its smoothing widened to half the coarse spacing so a thin surface between two
       coarse samples is still seen);
    3. ``n_fine`` samples drawn from those weights (``padding`` keeps a little mass everywhere).
    4. Each fine sample's segment runs to the next one but at most ``max_segment`` coarse
       spacings: the field's density at a sample is applied over its segment, so without the
       cap a sample in the faint tail of a surface the ray only grazes (the last sample, whose
       segment would run to ``far``, or one before a wide empty gap) makes the ray opaque. That
       dilated silhouettes by about one beta beyond VolSDF's own grazing-ray opacity and, with
       the mask loss, pulled the learnt surface inwards. The cap of 4 spacings keeps grazing-ray
       opacities past analytic spheres (radius 0.5 and 1, beta 0.005 and 0.02) within 0.15 of
       a dense float64 integral (``tests/test_sdf_grid.py``); uncapped they were up to 0.5 off.

    5. With ``anchor`` > 0, that many of the ``n_fine`` samples follow the FIELD's own first zero
       crossing instead of the cache's: the cache's first crossing along the coarse look-ups, refined
       by ``refine_evals`` evaluations of ``field.sdf`` (no grad) over +- one cache cell (one coarse
       spacing without a cache), then ``anchor`` stratified samples over ``anchor_window`` (in units
       of the density's transition width: ``beta``, or ``1/s`` for NeuS) around it. A transition
       narrower than the cache's error still gets its samples. Rays with no crossing draw them from
       the weights like the rest. ``eval_anchor`` (None: ``anchor``) is the count in evaluation renders (at
       most ``eval_n_fine - 1`` of them);
       ``anchor_when`` ``narrow`` uses them only while their window is narrower than a cache cell (wider
       transitions the cache resolves itself), ``always`` at every width. The defaults (none while training,
       8 in evaluation renders once narrow) gained validation PSNR on the development scenes
       (docs/measured/volsdf.md).

    Evaluation renders (gradients off) use ``eval_n_coarse`` / ``eval_n_fine`` (None: the training
    counts): more samples where no gradient is paid for.
    While training (gradients on) every ray keeps exactly ``n_fine`` samples; a ray that misses
    the box gets zero-length segments at its start (optical depth 0, background colour), so
    batches keep one shape. In evaluation renders (gradients off) a ray whose coarse opacity is
    below ``skip_opacity`` gets no fine sample at all: its colour is the background, which
    differs from the full render by at most about that opacity times the colour range, and
    saves the field's ``n_fine`` evaluations on every ray that passes no surface.
    ``samples_per_ray`` of this estimator (see :meth:`stats`) counts both passes.
    """

    def __init__(self, scene_box: Box, n_coarse: int = 128, n_fine: int = 16, resolution: int = 64,
                 every: int = 8, padding: float = 1e-3, skip_opacity: float = 1e-4, max_segment: float = 4.0,
                 eval_n_coarse: Optional[int] = None, eval_n_fine: Optional[int] = None, anchor: int = 0,
                 anchor_window: Sequence[float] = (-4.0, 3.0), refine_evals: int = 8,
                 eval_anchor: Optional[int] = 8, anchor_when: str = "narrow"):
        super().__init__(scene_box)
        eval_n_coarse = n_coarse if eval_n_coarse is None else eval_n_coarse
        eval_n_fine = n_fine if eval_n_fine is None else eval_n_fine
        self._check_anchor(anchor, anchor if eval_anchor is None else eval_anchor, anchor_window, refine_evals,
                           anchor_when, n_fine, eval_n_fine)
        if min(int(n_coarse), int(n_fine), int(eval_n_coarse), int(eval_n_fine)) < 2:
            raise UserError(f"n_coarse, n_fine, eval_n_coarse and eval_n_fine must be >= 2, got {n_coarse}, "
                             f"{n_fine}, {eval_n_coarse}, {eval_n_fine}")
        self.eval_n_coarse, self.eval_n_fine = int(eval_n_coarse), int(eval_n_fine)
        self._counts = (int(n_coarse), int(n_fine))
        if int(every) < 1:
            raise UserError(f"every must be >= 1 (steps between cache refreshes), got {every}")
        if not 0.0 <= float(skip_opacity) < 1.0:
            raise UserError(f"skip_opacity must be in [0, 1), got {skip_opacity}")
        self.n_coarse, self.n_fine, self.every, self.padding = int(n_coarse), int(n_fine), int(every), float(padding)
        if not float(max_segment) > 0:
            raise UserError(f"max_segment must be > 0 (coarse spacings), got {max_segment}")
        self.skip_opacity, self.max_segment = float(skip_opacity), float(max_segment)
        self._fine_fraction = 1.0
        self.cache = SDFGridCache(scene_box, int(resolution)) if int(resolution) > 1 else None
        self._fresh = False
        self._hit_fraction = 1.0
        self._refined_fraction = 0.0     # rays whose anchored samples were refined by the field (last batch)

    def _check_anchor(self, anchor, eval_anchor, window, refine_evals, when, n_fine, eval_n_fine) -> None:
        """Validate and keep the anchored samples' settings (step 5 of the class docstring)."""
        lo, hi = config_floats(window, "anchor_window", 2)
        if not (0 <= int(anchor) < int(n_fine) and 0 <= int(eval_anchor) and lo < hi
                and int(refine_evals) >= 2 and when in ("always", "narrow")):
            raise UserError(f"anchor must lie in [0, n_fine), eval_anchor be >= 0, anchor_window be "
                             f"[low, high] with low < high, refine_evals >= 2 and anchor_when always or narrow, got "
                             f"{anchor} ({eval_anchor}), {list(window)}, {refine_evals}, {when!r}")
        self.anchor, self.eval_anchor, self.anchor_window = int(anchor), int(eval_anchor), (lo, hi)
        self.refine_evals, self.anchor_when = int(refine_evals), str(when)

    def _update(self, step: int, field, generator, force: bool) -> None:
        if self.cache is not None and (force or not self._fresh or step % self.every == 0):
            self.cache.update(field.sdf)
            self._fresh = True

    def sampling(self, origins: torch.Tensor, dirs: torch.Tensor, *, perturb: bool = False,
                 generator: Optional[torch.Generator] = None, field=None, density=None, **field_kw) -> Samples:
        if density is None or (self.cache is None and field is None):
            raise ValueError("the sdf_cache estimator needs density= (and field= without a cache)")
        evaluating = not torch.is_grad_enabled()     # read before the no_grad block below
        n_coarse, n_fine = (self.eval_n_coarse, self.eval_n_fine) if evaluating else (self.n_coarse, self.n_fine)
        self._counts, self._refined_fraction = (n_coarse, n_fine), 0.0
        near, far, hit = self.bounds(origins, dirs)
        t_c = stratified_samples(near, far, n_coarse, perturb=perturb, generator=generator)
        with torch.no_grad():
            pts = origins[:, None, :] + t_c[..., None] * dirs[:, None, :]
            f_c = (self.cache if self.cache is not None else field.sdf)(pts.reshape(-1, 3)).reshape(t_c.shape)
            spacing = (far - near)[:, None] / max(n_coarse - 1, 1)
            w_c = _coarse_weights(density, f_c, t_c, far, 0.5 * spacing) * hit[:, None]
            edges = torch.cat([t_c, far[:, None]], dim=-1)   # each coarse sample owns [t_i, t_{i+1}]
            edges = torch.maximum(edges, torch.cat([edges[:, :1], edges[:, :-1]], dim=-1))
            n_anchor = min(self.eval_anchor if evaluating else self.anchor, n_fine - 1)
            if n_anchor > 0 and self.anchor_when == "narrow" and not self._window(density) < self._resolved(spacing):
                n_anchor = 0     # the cache (or the coarse pass) resolves the transition itself
            t = sample_pdf(edges, w_c, n_fine - n_anchor, perturb=perturb, generator=generator, padding=self.padding)
            if n_anchor > 0:     # step 5 above
                spare = sample_pdf(edges, w_c, n_anchor, perturb=perturb, generator=generator, padding=self.padding)
                t_anchor, found = self._anchored(origins, dirs, t_c, f_c, spacing[:, 0], hit, field, density,
                                                 n_anchor, perturb, generator)
                t_anchor = torch.minimum(torch.maximum(t_anchor, near[:, None]), far[:, None])
                t = torch.sort(torch.cat([t, torch.where(found[:, None], t_anchor, spare)], dim=-1), dim=-1).values
            keep = torch.ones_like(t, dtype=torch.bool)
            if self.skip_opacity > 0 and evaluating:     # evaluation: empty rays skip the field
                keep = (w_c.sum(-1) >= self.skip_opacity)[:, None].expand_as(t)
        self._hit_fraction = float(hit.float().mean())
        self._fine_fraction = float((keep[:, 0] & hit).float().mean())
        ends = torch.minimum(segment_ends(t, far), t + self.max_segment * spacing)   # step 4 above
        return pack_samples(t, ends, keep)

    def _anchored(self, origins, dirs, t_c, f_c, spacing, hit, field, density, n: int, perturb: bool, generator):
        """(R, n) samples around the field's first zero crossing and (R,) whether the cache saw one
        (on a ray inside the box, ``hit``)."""
        if field is None:
            raise ValueError("sdf_cache with anchor > 0 needs field= (its own SDF refines the crossing)")
        t_star, found = first_crossing(f_c, t_c)
        found = found & hit
        half = self._resolved(spacing)
        rays = found.nonzero()[:, 0]          # only rays the cache sees cross pay for the field's evaluations
        if rays.numel():
            t_star[rays] = refine_crossing(field.sdf, origins[rays], dirs[rays], t_star[rays], half,
                                           self.refine_evals)[0]
        self._refined_fraction = float(found.float().mean())
        width = transition_width(density)
        lo, hi = self.anchor_window
        k = torch.arange(n, dtype=t_c.dtype, device=t_c.device).expand(t_c.shape[0], n)
        u = (k + (rand(k.shape, generator, t_c.device, t_c.dtype) if perturb else 0.5)) / n
        return t_star[:, None] + width * (lo + (hi - lo) * u), found

    def _resolved(self, spacing: torch.Tensor) -> float:
        """The finest detail the coarse pass resolves (world units): a cache cell, or the widest coarse spacing."""
        return self.cache.cell_size if self.cache is not None else float(spacing.max())

    def _window(self, density) -> float:
        """Width of the anchored samples' window (world units)."""
        return (self.anchor_window[1] - self.anchor_window[0]) * transition_width(density)

    def stats(self) -> dict:
        """Evaluations per ray of the last batch, averaged over all rays: coarse (cache look-ups
        or SDF calls) + fine, and fine alone, counting rays inside the box (and, in evaluation
        renders, only those that kept their fine samples), with ``anchor`` the field's refining
        evaluations on the rays whose coarse pass found a crossing."""
        n_coarse, n_fine = self._counts
        refine = self._refined_fraction * self.refine_evals
        return {"samples_per_ray": self._hit_fraction * n_coarse + self._fine_fraction * n_fine + refine,
                "fine_samples_per_ray": self._fine_fraction * n_fine}


def _coarse_weights(density, sdf: torch.Tensor, t: torch.Tensor, far: torch.Tensor, widen: torch.Tensor
                    ) -> torch.Tensor:
    """(R, S) compositing weights of dense coarse samples under ``density`` (its smoothing
    widened to at least ``widen`` (R, 1) world units)."""
    n_rays, n = t.shape
    rays = torch.arange(n_rays, device=t.device).repeat_interleave(n)
    tau = density.optical_depth(sdf.reshape(-1), t.reshape(-1), segment_ends(t, far).reshape(-1), rays,
                                widen=widen.expand_as(t).reshape(-1)).reshape(t.shape)
    return composite(torch.zeros_like(t)[..., None], t, sigmas=tau, deltas=torch.ones_like(t))["weights"]
