"""train_nerf pieces: encodings, fields, occupancy skipping, data loaders, a short run."""

import json
import math

import numpy as np
import pytest
import torch

from l3d_app.app import run_task
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras, to_opengl_c2w
from l3d_app.models.encodings import HASH_PRIMES, GridEncoding, HarmonicEncoding
from l3d_app.models.nerf import GridField, NeRFMLP
from l3d_app.render.volume.estimators import OccupancyEstimator, StratifiedEstimator
from l3d_app.render.volume.occupancy import OccupancyGrid
from l3d_app.render.volume.radiance import render_field_rays
from conftest import course_data


# ------------------------------------------------------------------ encodings
def test_harmonic_encoding_matches_the_formula():
    enc = HarmonicEncoding(3, n_frequencies=4)
    x = torch.tensor([[0.3, -1.2, 2.0]], dtype=torch.float64)
    out = enc(x)
    assert out.shape == (1, 3 * 9) and enc.out_dim == 27
    torch.testing.assert_close(out[0, :3], x[0])
    for d in range(3):
        for k in range(4):
            f = 2.0 ** k
            assert math.isclose(float(out[0, 3 + d * 4 + k]), math.sin(f * float(x[0, d])), abs_tol=1e-12)
            assert math.isclose(float(out[0, 15 + d * 4 + k]), math.cos(f * float(x[0, d])), abs_tol=1e-12)


def _vertex_coords(enc: GridEncoding, level: int) -> torch.Tensor:
    """World coordinates (R^3, 3) of a dense level's vertices in table-row order."""
    r = int(enc.resolution[level])
    rows = torch.arange(r ** 3)
    ijk = torch.stack([rows % r, (rows // r) % r, rows // (r * r)], -1).double()
    return enc.lo.double() + ijk / (r - 1) * (enc.hi - enc.lo).double()


def test_grid_encoding_is_exact_on_a_linear_function():
    enc = GridEncoding(n_levels=3, n_features=2, base_resolution=4, max_resolution=9, log2_hashmap_size=20,
                       bounds=((-1.0, -2.0, 0.0), (1.0, 1.0, 3.0))).double()
    assert not bool(enc.hashed.any())
    a, b = torch.tensor([0.7, -1.3, 2.1], dtype=torch.float64), torch.tensor([-0.4, 0.25, 0.9], dtype=torch.float64)
    with torch.no_grad():
        for level in range(3):
            v = _vertex_coords(enc, level)
            s, n = int(enc.offsets[level]), v.shape[0]
            enc.table[s:s + n, 0] = v @ a + 1.0
            enc.table[s:s + n, 1] = v @ b - 2.0
    x = torch.rand(500, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    x = enc.lo.double() + x * (enc.hi - enc.lo).double()
    out = enc(x).reshape(500, 3, 2)
    for level in range(3):
        torch.testing.assert_close(out[:, level, 0], x @ a + 1.0, atol=1e-12, rtol=0)
        torch.testing.assert_close(out[:, level, 1], x @ b - 2.0, atol=1e-12, rtol=0)


def _naive_grid(enc: GridEncoding, x: torch.Tensor) -> torch.Tensor:
    """Per point, per level, per corner float64 reference (dense index or spatial hash)."""
    table = enc.table.detach().double()
    out = torch.zeros(x.shape[0], enc.n_levels, enc.n_features, dtype=torch.float64)
    lo, hi = enc.lo.double(), enc.hi.double()
    for n in range(x.shape[0]):
        u = ((x[n].double() - lo) / (hi - lo)).clamp(0, 1)
        for level in range(enc.n_levels):
            r = int(enc.resolution[level])
            p = [float(c) * (r - 1) for c in u]
            i0 = [min(int(math.floor(c)), r - 2) for c in p]
            for cx in (0, 1):
                for cy in (0, 1):
                    for cz in (0, 1):
                        c = (i0[0] + cx, i0[1] + cy, i0[2] + cz)
                        w = 1.0
                        for axis, bit in enumerate((cx, cy, cz)):
                            f = p[axis] - i0[axis]
                            w *= f if bit else 1 - f
                        if bool(enc.hashed[level]):
                            row = (c[0] * HASH_PRIMES[0] ^ c[1] * HASH_PRIMES[1] ^ c[2] * HASH_PRIMES[2]) % int(enc.sizes[level])
                        else:
                            row = c[0] + c[1] * r + c[2] * r * r
                        out[n, level] += w * table[int(enc.offsets[level]) + row]
    return out.reshape(x.shape[0], -1)


def test_grid_encoding_matches_a_naive_float64_reference_with_hashing():
    torch.manual_seed(0)
    enc = GridEncoding(n_levels=4, n_features=2, base_resolution=5, max_resolution=40, log2_hashmap_size=10,
                       bounds=((-1.0,) * 3, (1.0,) * 3), init_scale=1.0).double()
    assert bool(enc.hashed.any()) and not bool(enc.hashed.all())
    x = torch.rand(40, 3, dtype=torch.float64) * 2.4 - 1.2        # some points outside: clamped
    x[0] = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)     # the upper corner
    torch.testing.assert_close(enc(x), _naive_grid(enc, x), atol=1e-12, rtol=0)


def test_grid_field_gradients_are_finite():
    torch.manual_seed(0)
    field = GridField(scene_box=((-1.0,) * 3, (1.0,) * 3), n_levels=4, max_resolution=64, log2_hashmap_size=12,
                      use_viewdirs=True)
    x = (torch.rand(256, 3) * 2 - 1).requires_grad_()
    d = torch.nn.functional.normalize(torch.randn(256, 3), dim=-1)
    sigma, rgb = field(x, d)
    assert sigma.shape == (256,) and rgb.shape == (256, 3) and bool((sigma >= 0).all())
    (sigma.sum() + rgb.sum()).backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in field.parameters())
    assert bool(torch.isfinite(x.grad).all()) and float(field.encoding.table.grad.abs().sum()) > 0


def test_nerf_mlp_shapes_and_skip():
    model = NeRFMLP()
    assert model.trunk[3].in_features == 128 + model.enc_xyz.out_dim == 128 + 39
    sigma, rgb = model(torch.randn(10, 3), torch.nn.functional.normalize(torch.randn(10, 3), dim=-1))
    assert sigma.shape == (10,) and rgb.shape == (10, 3) and bool(((rgb > 0) & (rgb < 1)).all())


# ------------------------------------------------------------------ occupancy skipping
class BallField(torch.nn.Module):
    """Density 5 inside a ball of radius 0.4 at c, 0 outside; colour = f(position)."""

    def __init__(self):
        super().__init__()
        self.c = torch.tensor([0.1, -0.05, 0.0])
        self.calls = 0

    def density(self, p):
        return 5.0 * ((p - self.c).norm(dim=-1) < 0.4).float()

    def forward(self, p, d):
        self.calls += p.shape[0]
        return self.density(p), torch.sigmoid(3 * p)


def _rays(n=400):
    cams = look_at_cameras(2.5, 20.0, 30.0, 45.0, 20)
    from l3d_app.geometry.rays import camera_rays
    o, d = camera_rays(cams)
    return o.reshape(-1, 3)[:n], d.reshape(-1, 3)[:n]


BOX = ((-1.0,) * 3, (1.0,) * 3)


def test_all_occupied_grid_renders_exactly_like_no_grid():
    o, d = _rays()
    field = BallField()
    est = OccupancyEstimator(BOX, n_samples=64, resolution=16)
    assert est.grid.occupied_fraction == 1.0
    a = render_field_rays(field, o, d, StratifiedEstimator(64, scene_box=BOX), background=(1.0, 1.0, 1.0))
    b = render_field_rays(field, o, d, est, background=(1.0, 1.0, 1.0))
    for k in ("color", "depth", "opacity"):
        assert torch.equal(a[k], b[k])
    assert float(a["opacity"].max()) > 0.9 and float(a["opacity"].min()) < 0.01   # the ball is in view


def test_occupancy_grid_skips_empty_samples_without_changing_the_render():
    o, d = _rays()
    field = BallField()
    est = OccupancyEstimator(BOX, n_samples=64, resolution=16)
    grid = est.grid
    # occupied = cells whose box touches the ball (conservative, exact cover)
    half = (grid.hi - grid.lo) / grid.resolution / 2
    gap = ((grid.cell_centers() - field.c).abs() - half).clamp_min(0).norm(dim=-1)
    grid.mask.copy_(gap < 0.4)
    assert 0.02 < grid.occupied_fraction < 0.3
    field.calls = 0
    dense = render_field_rays(field, o, d, StratifiedEstimator(64, scene_box=BOX), background=(1.0, 1.0, 1.0))
    dense_calls, field.calls = field.calls, 0
    skip = render_field_rays(field, o, d, est, background=(1.0, 1.0, 1.0))
    assert field.calls < 0.5 * dense_calls
    assert float(skip["samples_per_ray"]) * o.shape[0] == pytest.approx(field.calls)
    torch.testing.assert_close(skip["color"], dense["color"], atol=1e-6, rtol=0)
    torch.testing.assert_close(skip["depth"], dense["depth"], atol=1e-5, rtol=0)


def test_occupancy_update_marks_dense_cells_after_warmup():
    field = BallField()
    grid = OccupancyGrid(BOX, resolution=16, threshold=1.0, warmup_steps=10, update_every=1)
    grid.update(field.density, step=0, generator=torch.Generator().manual_seed(0))
    assert grid.occupied_fraction == 1.0                      # warm-up: everything occupied
    grid.update(field.density, step=20, generator=torch.Generator().manual_seed(1))
    centres = grid.cell_centers()
    dist = (centres - field.c).norm(dim=-1)
    assert bool(grid.mask[dist < 0.2].all()) and not bool(grid.mask[dist > 0.6].any())
    assert 0.01 < grid.occupied_fraction < 0.2
    state = grid.state_dict()
    other = OccupancyGrid(BOX, resolution=16)
    other.load_state_dict(state)
    assert torch.equal(other.mask, grid.mask)


# ------------------------------------------------------------------ data loaders
def _write_blender(root, cams, images_rgba, split_counts=(("train", 2), ("test", 1)), drop_key=None):
    import imageio.v2 as imageio

    c2w = to_opengl_c2w(cams)
    fov_x = 2 * math.atan(cams.width / 2 / float(cams.fx[0]))
    i = 0
    for split, n in split_counts:
        frames = []
        for _ in range(n):
            (root / split).mkdir(parents=True, exist_ok=True)
            imageio.imwrite(root / split / f"r_{i}.png", images_rgba[i])
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w[i].tolist()})
            i += 1
        meta = {"camera_angle_x": fov_x, "frames": frames}
        if drop_key and split == "train":
            meta.pop(drop_key)
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))


def test_blender_loader_round_trips_cameras_and_composites_alpha(tmp_path):
    from l3d_app.data.nerf_formats import blender

    cams = look_at_cameras(4.0, torch.tensor([10.0, 30.0, -5.0]), torch.tensor([0.0, 120.0, 250.0]), 40.0, 8)
    rgba = np.random.default_rng(0).integers(0, 256, (3, 8, 8, 4)).astype(np.uint8)
    rgba[:, 0, 0, 3] = 0
    rgba[:, 0, 1, 3] = 255
    _write_blender(tmp_path, cams, rgba)
    for bg in ("white", "black"):
        data = blender(str(tmp_path), background=bg)
        assert data.images.shape == (3, 8, 8, 3)
        assert data.train.tolist() == [0, 1] and data.test.tolist() == [2] and len(data.val) == 0
        torch.testing.assert_close(data.cameras.R, cams.R, atol=1e-5, rtol=0)
        torch.testing.assert_close(data.cameras.t, cams.t, atol=1e-5, rtol=0)
        torch.testing.assert_close(data.cameras.fx, cams.fx, atol=1e-4, rtol=0)
        expect = 1.0 if bg == "white" else 0.0
        assert torch.allclose(data.images[:, 0, 0], torch.full((3, 3), expect))
        torch.testing.assert_close(data.images[:, 0, 1], torch.from_numpy(rgba[:, 0, 1, :3] / 255.0).float())
        # the alpha channel is kept as the views' coverage masks
        torch.testing.assert_close(data.masks, torch.from_numpy(rgba[..., 3] / 255.0).float())
    half = blender(str(tmp_path), downscale=2)
    assert half.images.shape == (3, 4, 4, 3) and float(half.cameras.fx[0]) == pytest.approx(float(cams.fx[0]) / 2, rel=1e-5)
    # downscaled coverage is the mean alpha of each 2x2 block
    torch.testing.assert_close(half.masks, torch.from_numpy(rgba[..., 3] / 255.0).float().reshape(3, 4, 2, 4, 2).mean((2, 4)))
    # RGB images have no masks
    _write_blender(tmp_path / "rgb", cams, rgba[..., :3].copy())
    assert blender(str(tmp_path / "rgb")).masks is None


def test_blender_loader_reports_missing_keys_and_files(tmp_path):
    from l3d_app.data.nerf_formats import blender

    cams = look_at_cameras(4.0, 10.0, torch.tensor([0.0, 90.0, 180.0]), 40.0, 8)
    rgba = np.zeros((3, 8, 8, 4), dtype=np.uint8)
    _write_blender(tmp_path, cams, rgba, drop_key="camera_angle_x")
    with pytest.raises(UserError, match="camera_angle_x"):
        blender(str(tmp_path))
    with pytest.raises(UserError, match="not found"):
        blender(str(tmp_path / "nope"))
    (tmp_path / "transforms_test.json").unlink()
    _write_blender(tmp_path, cams, rgba)
    (tmp_path / "test" / "r_2.png").unlink()
    with pytest.raises(UserError, match="r_2.png"):
        blender(str(tmp_path))


def test_truck_loads_with_the_course_split():
    from l3d_app.data.nerf_formats import truck

    data = truck(str(course_data("truck")))
    assert data.images.shape == (202, 90, 160, 3)
    assert data.test.tolist() == [33, 67, 101, 134, 168] and len(data.train) + len(data.val) == 197
    assert not set(data.val.tolist()) & set(data.test.tolist()) and len(data.val) > 0
    assert float(data.cameras.fx[0]) == pytest.approx(74.6, abs=0.5)
    assert bool((data.scene_box[1] > data.scene_box[0]).all())


# ------------------------------------------------------------------ the task
TINY = ["data.image_size=32", "data.n_train=48", "data.n_val=2", "data.n_test=2", "data.antialias=1",
        "tensorboard=false", "threads=1"]


def test_train_nerf_short_run_improves_psnr(compose, tmp_path, data_cache):
    cfg = compose("task=train_nerf", *TINY, f"data.cache_dir={data_cache}", "iters=240", "eval_every=60",
                  "batch_rays=512", "sampler.n_samples=48", "sampler.resolution=32", "sampler.warmup_steps=40",
                  "sampler.update_every=8", "sampler.threshold=2.0", "gif_frames=3", "extract_mesh=true",
                  "mesh_resolution=32", "mesh_threshold=2.0", "mesh_formats=[obj,glb]")
    run_task(cfg, out_dir=tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    for key in ("psnr", "ssim", "val_psnr", "val_ssim", "seconds", "iters", "n_params", "occupied_fraction",
                "samples_per_ray", "rays_per_second"):
        assert key in m
    hist = [h["psnr"] for h in m["history"]]            # validation views only
    assert m["history"][-1]["psnr"] == pytest.approx(m["val_psnr"], abs=1e-3)
    assert m["iters"] == 240 and len(hist) == 4
    assert hist[-1] > hist[0] + 1.5 and m["psnr"] > 19.0, hist
    assert m["occupied_fraction"] < 0.6 and m["samples_per_ray"] < 48
    for name in ("turntable.gif", "test_views.png", "checkpoint.pt", "mesh.obj", "mesh.glb"):
        assert (tmp_path / "run" / name).exists(), name
    assert m["mesh_faces"] > 100
    assert (tmp_path / "run" / "before_after.png").exists() and m["before_val_psnr"] < hist[0] < m["val_psnr"]


def test_nerf_baseline_config_is_the_course_setting(compose, tmp_path, data_cache):
    cfg = compose("task=nerf_baseline")
    assert cfg.task_name == "train_nerf" and cfg.model.name == "nerf_mlp"
    assert (cfg.model.n_layers, cfg.model.hidden, list(cfg.model.skips)) == (6, 128, [3])
    assert (cfg.model.n_freq_xyz, cfg.model.n_freq_dir, cfg.sampler.n_samples, cfg.batch_rays) == (6, 2, 64, 1024)
    assert (cfg.optim.lr, cfg.optim.decay, cfg.optim.decay_every, cfg.sampler.name) == (5e-4, 0.8, 20000, "hierarchical")
    assert cfg.sampler.n_fine == 128
    assert (cfg.optim.name, cfg.optim.eps, cfg.optim.decay_every) == ("adam_step", 1e-8, 20000)
    cfg = compose("task=nerf_baseline", *TINY, f"data.cache_dir={data_cache}", "iters=3", "eval_every=3",
                  "batch_rays=64", "sampler.n_samples=16", "sampler=importance", "sampler.n_fine=8", "gif_frames=0")
    run_task(cfg, out_dir=tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["iters"] == 3 and "occupied_fraction" not in m and math.isfinite(m["psnr"])
    assert 8 < m["samples_per_ray"] <= 16 + 8          # importance: coarse 16 + fine 8 rendered per ray in the box


def test_builtin_cameras_follow_the_elevation_range():
    from l3d_app.data.nerf_views import builtin_cameras

    for lo, hi in ((-10.0, 70.0), (-50.0, 70.0)):
        cams, tr, va, te = builtin_cameras(60, 2, 3, 16, 3.2, 45.0, (lo, hi))
        elev = torch.rad2deg(torch.asin(cams.centers()[tr, 1].double() / 3.2))
        assert elev.min() > lo and elev.max() < hi
        assert elev.min() < lo + 3 and elev.max() > hi - 6          # spread over the whole range
        assert len(va) == 2 and len(te) == 3
    with pytest.raises(UserError):
        builtin_cameras(10, 1, 1, 16, 3.2, 45.0, (20.0, -10.0))


def test_orbit_cameras_circle_the_given_up_axis_and_cameras_up_finds_it():
    from l3d_app.render.turntable import cameras_up, orbit_cameras

    for up in ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (1.0, 2.0, -0.5)):
        u = torch.tensor(up) / torch.tensor(up).norm()
        at = torch.tensor([0.3, -0.2, 0.1])
        cams = orbit_cameras(8, 3.0, 30.0, 40.0, 16, up=up, at=at.tolist())
        rel = cams.centers() - at
        # every centre: distance 3, height 3 sin(30) along up, and the orbit spans the plane
        torch.testing.assert_close(rel.norm(dim=-1), torch.full((8,), 3.0), atol=1e-4, rtol=0)
        torch.testing.assert_close(rel @ u, torch.full((8,), 1.5), atol=1e-4, rtol=0)
        # each camera looks at ``at`` and its image-up leans toward ``up``
        fwd = cams.R[:, 2, :]
        torch.testing.assert_close(fwd, -rel / 3.0, atol=1e-4, rtol=0)
        assert bool(((-cams.R[:, 1, :]) @ u > 0.5).all())
        torch.testing.assert_close(cameras_up(cams), u if max(abs(v) for v in up) == 1.0 else cameras_up(cams))
    # a +Z-up orbit's mean up vector snaps to +Z
    torch.testing.assert_close(cameras_up(orbit_cameras(12, 3.0, 20.0, 40.0, 16, up=(0, 0, 1))),
                               torch.tensor([0.0, 0.0, 1.0]))


def test_nerf_mlp_omega0_sets_the_position_frequencies(compose):
    cfg = compose("task=nerf_baseline", "model.omega0=3.141592653589793")
    m = NeRFMLP(**{k: v for k, v in cfg.model.items() if k != "name"})
    x = torch.tensor([[0.25, -0.5, 0.125]])
    out = m.enc_xyz(x)
    for k in range(6):       # sin(pi 2^k x_0) sits at column 3 + 0 * 6 + k
        assert math.isclose(float(out[0, 3 + k]), math.sin(math.pi * 2 ** k * 0.25), abs_tol=1e-5)
    with pytest.raises(ValueError):
        NeRFMLP(omega0=0.0)
