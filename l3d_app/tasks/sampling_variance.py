"""sampling_variance: uniform, evenly spaced and stratified samples along a ray -- the variance of the
estimated optical depth against the number of samples per ray, measured over many rays beside the closed forms.

Two densities along a unit ray over ``[near, far]``: a slab of constant density (a hard
surface-like edge; exact variances for both samplers) and a Gaussian bump (smooth; exact
for uniform sampling, measured for stratified). For each ``n_samples`` in ``samples``,
``rays`` independent rays give the estimates (:mod:`l3d_app.render.volume.sampling_variance`).
Evenly spaced samples (the course's exercise) put the same samples on every ray of the same length: their
estimate's spread across rays and the spread of their sample positions are exactly 0, and what they get
wrong is a fixed error (``evenly_error``), where stratified samples have a spread (``stratified_spread``:
their positions' standard deviation, ``(far - near) / (N sqrt 12)`` on average) and no bias.
Writes ``variance.png`` (log-log, measured points and exact lines), ``table.md`` and
metrics.json: one row per (density, N) and the fitted log-log slopes (uniform -1; stratified
-2 on the slab, -3 on the bump).
"""

from __future__ import annotations

from l3d_app.errors import UserError
from l3d_app.registry import TASKS
from l3d_app.render.volume.sampling_variance import (GaussianBump, Slab, estimates_at, loglog_slope,
                                                     position_spread, sample_positions, stratified_variance_slab,
                                                     uniform_variance)
from l3d_app.runtime.plots import line_plot
from l3d_app.tasks.common import require_positive


@TASKS.register("sampling_variance")
def sampling_variance(cfg, ctx) -> dict:
    """Measure both samplers on both densities over the sample counts; table, plot, slopes."""
    require_positive(cfg, "rays", "far")
    if not float(cfg.slab.end) > float(cfg.slab.start):
        raise UserError(f"slab.end must be greater than slab.start, got {cfg.slab.start} .. {cfg.slab.end}")
    if float(cfg.slab.density) < 0 or float(cfg.bump.density) < 0 or float(cfg.bump.width) <= 0:
        raise UserError("slab.density and bump.density must be >= 0 and bump.width > 0")
    near, far = float(cfg.near), float(cfg.far)
    ns = [int(n) for n in cfg.samples]
    if not ns or min(ns) < 2 or not 0 <= near < far:
        raise UserError(f"need samples all >= 2 and 0 <= near < far, got samples={ns}, near={near}, far={far}")
    densities = {"slab": Slab(float(cfg.slab.start), float(cfg.slab.end), float(cfg.slab.density)),
                 "bump": GaussianBump(float(cfg.bump.centre), float(cfg.bump.width), float(cfg.bump.density))}
    rows, curves, points, metrics = [], {}, {}, {}
    for name, density in densities.items():
        tau = density.integral(near, far)
        measured = {m: [] for m in ("uniform", "stratified")}
        for n in ns:
            row = {"density": name, "n_samples": n, "tau": round(tau, 6)}
            for method in (*measured, "evenly"):
                t = sample_positions(near, far, n, int(cfg.rays), method, ctx.generator)
                est = estimates_at(density, t, near, far, method)
                row[f"{method}_mean"] = round(float(est.mean()), 6)
                row[f"{method}_var"] = float(est.var())
                row[f"{method}_range"] = float(est.max() - est.min())      # across rays: exactly 0 when equal
                row[f"{method}_spread"] = round(position_spread(t), 6)
                if method in measured:
                    measured[method].append(float(est.var()))
            row["evenly_error"] = round(row["evenly_mean"] - tau, 6)
            row["uniform_var_exact"] = uniform_variance(density, near, far, n)
            if isinstance(density, Slab):
                row["stratified_var_exact"] = stratified_variance_slab(density, near, far, n)
            rows.append(row)
            ctx.logger.log_scalars({f"sampling_variance/{name}_uniform": measured["uniform"][-1],
                                    f"sampling_variance/{name}_stratified": measured["stratified"][-1]}, step=n)
        for method in measured:
            points[f"{name} {method} (measured)"] = (ns, measured[method])
            metrics[f"{name}_{method}_slope"] = round(loglog_slope(ns, measured[method]), 4)
        curves[f"{name} uniform"] = (ns, [r["uniform_var_exact"] for r in rows if r["density"] == name])
        if isinstance(density, Slab):
            curves[f"{name} stratified"] = (ns, [r["stratified_var_exact"] for r in rows if r["density"] == name])
    line_plot(ctx.path("variance.png"), curves, points, xlabel="samples per ray N",
              ylabel="variance of the optical-depth estimate", logx=True, logy=True,
              title=f"{cfg.rays} rays per point; lines: exact")
    head = "| density | N | uniform var | exact | stratified var | exact | uniform mean | stratified mean | tau |\n" \
           "|---|---|---|---|---|---|---|---|---|\n"
    body = "".join(f"| {r['density']} | {r['n_samples']} | {r['uniform_var']:.4g} | {r['uniform_var_exact']:.4g} | "
                   f"{r['stratified_var']:.4g} | {r.get('stratified_var_exact', float('nan')):.4g} | "
                   f"{r['uniform_mean']:.4f} | {r['stratified_mean']:.4f} | {r['tau']:.4f} |\n" for r in rows)
    even = "\n| density | N | evenly spaced: estimate | its error | range across rays | sample-position " \
           "spread | stratified: mean | range across rays | sample-position spread |\n|---|---|---|---|---|---|---|---|---|\n"
    even += "".join(f"| {r['density']} | {r['n_samples']} | {r['evenly_mean']:.4f} | {r['evenly_error']:+.4f} | "
                    f"{r['evenly_range']:.3g} | {r['evenly_spread']:.3g} | {r['stratified_mean']:.4f} | "
                    f"{r['stratified_range']:.4g} | {r['stratified_spread']:.4g} |\n" for r in rows)
    ctx.path("table.md").write_text(head + body + even)
    print(f"evenly spaced against stratified samples ({cfg.rays} rays of length {far - near:g}):{even}", flush=True)
    metrics["evenly_max_spread"] = max(max(r["evenly_range"], r["evenly_spread"]) for r in rows)
    return {**metrics, "rays": int(cfg.rays), "rows": rows}
