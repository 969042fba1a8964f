"""sampler=hierarchical: NeRF's coarse + fine networks. The inverse-CDF draw against a naive per-ray one,
the coarse weights against a float64 loop, where the gradients go, and a short run's quality floor."""

import json
import math

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.render.volume.estimators import HierarchicalEstimator
from l3d_app.render.volume.samplers import bin_edges, sample_pdf

D = torch.float64


def _naive_inverse_cdf(edges, weights, u, padding):
    """Per ray, per level: walk the bins until the cumulative mass passes u, then interpolate."""
    out = torch.zeros(u.shape, dtype=D)
    for r in range(weights.shape[0]):
        w = [float(x) + padding for x in weights[r]]
        total = sum(w)
        for k in range(u.shape[1]):
            acc = 0.0
            for j, wj in enumerate(w):
                p = wj / total
                if acc + p > float(u[r, k]) or j == len(w) - 1:
                    out[r, k] = float(edges[r, j]) + (float(u[r, k]) - acc) / p * float(edges[r, j + 1] - edges[r, j])
                    break
                acc += p
    return out


def test_inverse_cdf_draw_matches_a_naive_one():
    g = torch.Generator().manual_seed(0)
    t = torch.sort(1.0 + 3.0 * torch.rand(3, 12, generator=g, dtype=D), dim=-1).values
    w = torch.rand(3, 12, generator=g, dtype=D) ** 4
    w[1] = 0.0                                                     # an empty ray: the padding alone
    edges = bin_edges(t, 1.0, 4.0)
    n = 20
    k = torch.arange(n, dtype=D).expand(3, n)
    fixed = sample_pdf(edges, w, n, perturb=False, padding=1e-3)
    torch.testing.assert_close(fixed, _naive_inverse_cdf(edges, w, (k + 0.5) / n, 1e-3))
    jitter = torch.rand(3, n, generator=torch.Generator().manual_seed(7), dtype=D)
    drawn = sample_pdf(edges, w, n, perturb=True, generator=torch.Generator().manual_seed(7), padding=1e-3)
    torch.testing.assert_close(drawn, _naive_inverse_cdf(edges, w, (k + jitter) / n, 1e-3))


class _Bump(torch.nn.Module):
    """Density peak * exp(-((z - 2.5) / 0.1)^2) (a slab across z = 2.5), colour (z, 0.5, 0.5) scaled."""

    def __init__(self):
        super().__init__()
        self.peak = torch.nn.Parameter(torch.tensor(30.0, dtype=D))
        self.tint = torch.nn.Parameter(torch.tensor(0.2, dtype=D))

    def density(self, p):
        return self.peak * torch.exp(-((p[:, 2] - 2.5) / 0.1) ** 2)

    def forward(self, p, d):
        rgb = torch.stack([self.tint * p[:, 2], 0.5 + 0 * p[:, 2], 0.5 + 0 * p[:, 2]], -1)
        return self.density(p), rgb


def _rays(n=6):
    o = torch.zeros(n, 3, dtype=D)
    o[:, 0] = torch.linspace(-0.5, 0.5, n, dtype=D)
    return o, torch.tensor([[0.0, 0.0, 1.0]], dtype=D).expand(n, 3).contiguous()


def test_fine_samples_come_from_the_coarse_weights():
    est = HierarchicalEstimator(n_samples=16, n_fine=24, padding=1e-5, near=1.0, far=4.0)
    est.attach_fields(_Bump)
    o, d = _rays()
    with torch.no_grad():
        t0, t1, rays = est.sampling(o, d)
    t = t0.reshape(6, 40)
    coarse = torch.linspace(1.0, 4.0, 16, dtype=D)
    is_coarse = (t[..., None] - coarse).abs().min(-1).values < 1e-12
    fine = t[~is_coarse].reshape(6, 24)
    # the coarse weights by a float64 loop: T_i = prod_{j<i} exp(-sigma_j delta_j), w_i = T_i (1 - exp(-sigma_i delta_i))
    sigma = 30.0 * torch.exp(-((coarse - 2.5) / 0.1) ** 2)
    ends = torch.cat([coarse[1:], torch.tensor([4.0], dtype=D)])
    w, trans = [], 1.0
    for s, a, b in zip(sigma.tolist(), coarse.tolist(), ends.tolist()):
        w.append(trans * (1 - math.exp(-s * (b - a))))
        trans *= math.exp(-s * (b - a))
    w = torch.tensor(w, dtype=D).expand(6, 16)
    k = torch.arange(24, dtype=D).expand(6, 24)
    expect = _naive_inverse_cdf(bin_edges(coarse.expand(6, 16), 1.0, 4.0), w, (k + 0.5) / 24, 1e-5)
    torch.testing.assert_close(fine, expect)
    assert ((fine > 2.2) & (fine < 2.8)).double().mean() > 0.8         # concentrated at the slab
    assert t1.shape == t0.shape and (t1 >= t0).all() and rays.tolist() == torch.arange(6).repeat_interleave(40).tolist()


def test_coarse_loss_trains_the_coarse_network_only():
    est = HierarchicalEstimator(n_samples=16, n_fine=8, near=1.0, far=4.0)
    est.attach_fields(_Bump)
    fine = _Bump()
    o, d = _rays()
    t0, t1, rays = est.sampling(o, d, background=torch.ones(3, dtype=D))
    target = torch.full((6, 3), 0.3, dtype=D)
    coarse_loss = est.training_loss(target)
    assert est.training_loss(target) is None                         # read once
    # the fine pass: its loss reaches the fine network, never the coarse one (the draw is detached)
    from l3d_app.render.volume.rendering import radiance_fn, render_rays
    out = render_rays(t0, t1, rays, 6, radiance_fn(fine, o, d), background=torch.ones(3, dtype=D))
    fine_loss = (out["color"] - target).square().mean()
    (coarse_loss + fine_loss).backward()
    assert est.coarse.tint.grad is not None and est.coarse.tint.grad.abs() > 0
    assert fine.tint.grad.abs() > 0
    est.coarse.zero_grad()
    fine.zero_grad()
    out = render_rays(t0, t1, rays, 6, radiance_fn(fine, o, d))
    out["color"].sum().backward()
    assert est.coarse.tint.grad is None or float(est.coarse.tint.grad.abs()) == 0.0
    with torch.no_grad():                                            # evaluation: no colour kept, no loss
        est.sampling(o, d)
    assert est.training_loss(target) is None


TINY = ["data.image_size=32", "data.n_train=48", "data.n_val=2", "data.n_test=2", "data.antialias=1",
        "tensorboard=false", "threads=1"]


def test_experiment_nerf_baseline_is_hierarchical_and_a_short_run_learns(compose, tmp_path, data_cache):
    cfg = compose("experiment=nerf_baseline")
    assert (cfg.sampler.name, cfg.sampler.n_samples, cfg.sampler.n_fine, cfg.model.name) == \
        ("hierarchical", 64, 128, "nerf_mlp")
    cfg = compose("task=train_nerf", "sampler=hierarchical", *TINY, f"data.cache_dir={data_cache}",
                  "iters=120", "eval_every=60", "batch_rays=256", "sampler.n_samples=16", "sampler.n_fine=16", "gif_frames=0",
                  "before_after=false", "time_budget=0")
    run_task(cfg, out_dir=tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    single = compose("task=train_nerf", *TINY)
    from l3d_app.registry import MODELS
    import l3d_app.models  # noqa: F401
    n_one = sum(p.numel() for p in MODELS.build(single.model, scene_box=single.data.scene_box).parameters())
    assert m["n_params"] == 2 * n_one and m["coarse_samples_per_ray"] == 16
    assert 16 < m["samples_per_ray"] <= 32                           # coarse + fine samples on rays in the box
    # the white background alone reads about 12 dB here; the coarse network learns too (its own loss)
    assert m["psnr"] > 17.0 and m["history"][-1]["psnr"] > m["history"][0]["psnr"], m["history"]
    assert -10 * math.log10(m["coarse_train_mse"]) > 15.0
