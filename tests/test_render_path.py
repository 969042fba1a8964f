"""Camera paths about an arbitrary up axis (orbit, spiral, slerp + Catmull-Rom interpolation,
nerfstudio camera_path.json) and task=render_path on trained gs_train, train_nerf and volsdf runs and a PLY."""

import json
import math

import imageio.v2 as imageio
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from l3d_app.app import run_task
from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import (catmull_rom, interpolate_cameras, orbit, quaternion_to_rotation,
                                           read_camera_path, rotation_to_quaternion, slerp, spiral,
                                           write_camera_path)
from l3d_app.geometry.cameras import look_at_cameras

UP = torch.tensor([1.0, 2.0, 2.0]) / 3.0
CENTRE = torch.tensor([0.5, -0.2, 0.3])


def _elevation(cams):
    off = cams.centers().double() - CENTRE.double()
    return torch.rad2deg(torch.asin((off / off.norm(dim=-1, keepdim=True)) @ UP.double()))


def test_orbit_about_a_tilted_up_axis_looks_at_the_centre_upright():
    cams = orbit(12, CENTRE, UP, 2.5, 30.0, 50.0, 40, 30)
    off = cams.centers().double() - CENTRE.double()
    torch.testing.assert_close(off.norm(dim=-1), torch.full((12,), 2.5, dtype=torch.float64), atol=1e-5, rtol=0)
    torch.testing.assert_close(_elevation(cams), torch.full((12,), 30.0, dtype=torch.float64), atol=1e-3, rtol=0)
    uv, z = cams.project(CENTRE[None])
    torch.testing.assert_close(uv[:, 0], torch.tensor([[20.0, 15.0]]).expand(12, 2), atol=1e-3, rtol=0)
    uv_up, _ = cams.project((CENTRE + 0.1 * UP)[None])
    assert bool((uv_up[:, 0, 1] < 15.0 - 1.0).all())              # up is up in every image
    # consecutive cameras 30 degrees apart about the up axis
    flat = off - (off @ UP.double())[:, None] * UP.double()
    cosang = torch.nn.functional.cosine_similarity(flat, flat.roll(-1, 0), dim=-1)
    torch.testing.assert_close(cosang, torch.full((12,), math.cos(math.radians(30)), dtype=torch.float64), atol=1e-5, rtol=0)


def test_spiral_swings_elevation_within_its_amplitude():
    cams = spiral(40, CENTRE, UP, 2.0, 20.0, 50.0, 16, 16, rounds=2, elevation_amplitude=10.0, radius_amplitude=0.1)
    el = _elevation(cams)
    assert float(el.min()) >= 10.0 - 1e-3 and float(el.max()) <= 30.0 + 1e-3 and float(el.max() - el.min()) > 19.0
    r = (cams.centers().double() - CENTRE.double()).norm(dim=-1)
    assert float(r.min()) >= 1.8 - 1e-4 and float(r.max()) <= 2.2 + 1e-4


def test_quaternions_match_scipy_and_slerp_halves_the_angle():
    R = torch.from_numpy(Rotation.random(50, random_state=0).as_matrix())
    R = torch.cat([R, torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))[None]])   # w = 0 case
    q = rotation_to_quaternion(R)
    ref = Rotation.from_matrix(R.numpy()).as_quat()[:, [3, 0, 1, 2]]                              # (w, x, y, z)
    ref = ref * np.sign(ref[:, :1] + 1e-15)
    np.testing.assert_allclose(np.abs((q.numpy() * ref).sum(-1)), 1.0, atol=1e-12)
    torch.testing.assert_close(quaternion_to_rotation(q), R, atol=1e-12, rtol=0)
    a = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64)
    b = torch.tensor([[math.cos(1.0), 0, 0, math.sin(1.0)]], dtype=torch.float64)   # 2 rad about z
    m = slerp(a, b, torch.tensor([0.25], dtype=torch.float64))
    torch.testing.assert_close(m, torch.tensor([[math.cos(0.25), 0, 0, math.sin(0.25)]], dtype=torch.float64))
    # shorter arc: -b is the same rotation
    torch.testing.assert_close(slerp(a, -b, torch.tensor([0.25], dtype=torch.float64)), m)


def test_catmull_rom_passes_through_points_and_is_linear_on_a_line():
    P = torch.tensor([[0.0, 0, 0], [1, 2, 0], [3, 1, 1], [4, 4, 2]], dtype=torch.float64)
    torch.testing.assert_close(catmull_rom(P, torch.arange(4, dtype=torch.float64)), P)
    line = torch.arange(5, dtype=torch.float64)[:, None] * torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64)
    s = torch.linspace(1, 3, 9, dtype=torch.float64)            # interior segments: exactly linear
    torch.testing.assert_close(catmull_rom(line, s), s[:, None] * line[1])


def test_interpolation_hits_the_keys_and_moves_smoothly():
    keys = look_at_cameras(3.0, torch.tensor([10.0, 40.0, 20.0, 0.0]), torch.tensor([0.0, 90.0, 180.0, 270.0]), 50.0, 16)
    cams = interpolate_cameras(keys, 16, closed=True)                  # 4 frames per segment
    for k in range(4):
        torch.testing.assert_close(cams.R[4 * k], keys.R[k], atol=1e-5, rtol=0)
        torch.testing.assert_close(cams.centers()[4 * k], keys.centers()[k], atol=1e-5, rtol=0)
    rel = cams.R.double() @ cams.R.roll(-1, 0).double().transpose(1, 2)
    angle = torch.rad2deg(torch.acos(((rel.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert float(angle.max()) < 30.0 and float(angle.min()) > 5.0


def test_camera_path_json_round_trip_and_faults(tmp_path):
    cams = orbit(5, CENTRE, UP, 2.0, 10.0, 40.0, 32, 24)
    write_camera_path(tmp_path / "p.json", cams)
    back = read_camera_path(tmp_path / "p.json")
    torch.testing.assert_close(back.R, cams.R, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.t, cams.t, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.fy, cams.fy, atol=1e-4, rtol=0)
    meta = json.loads((tmp_path / "p.json").read_text())
    meta["camera_path"] = []
    (tmp_path / "empty.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match=r"empty.json: no keyframes"):
        read_camera_path(tmp_path / "empty.json")
    meta = json.loads((tmp_path / "p.json").read_text())
    meta["camera_path"][3]["camera_to_world"][5] = float("nan")
    (tmp_path / "nan.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match=r"nan.json: frame 3: camera pose has a non-finite"):
        read_camera_path(tmp_path / "nan.json")
    meta["camera_path"][3]["camera_to_world"][5] = 3.0               # scaled column: not rigid
    (tmp_path / "scaled.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match=r"scaled.json: frame 3: camera rotation is not rigid"):
        read_camera_path(tmp_path / "scaled.json")


def test_render_path_on_a_gs_train_run_matches_the_model(compose, tmp_path, data_cache):
    from omegaconf import OmegaConf

    from l3d_app.data.nerf_views import nerf_builtin
    from l3d_app.geometry.gaussian_ply import load_gaussian_ply
    from l3d_app.models.gaussians import GaussianModel
    from l3d_app.render.gaussians.rasterize import rasterize_gaussians

    data_args = ["data.image_size=24", "data.n_train=12", "data.n_val=1", "data.n_test=1", "data.antialias=1",
                 f"data.cache_dir={data_cache}"]
    run = tmp_path / "gs"
    cfg = compose("task=gs_train", *data_args, "iters=6", "eval_every=6", "n_init=300", "tensorboard=false",
                  "threads=1", "sh_degree=0")
    run_task(cfg, out_dir=run)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    rp = compose("task=render_path", f"checkpoint={run}", "path=interp", "num_frames=8", "interp_keys=4",
                 "tensorboard=false", "threads=1")
    run_task(rp, out_dir=tmp_path / "rp")
    gif = imageio.mimread(tmp_path / "rp" / "path.gif")
    assert len(gif) == 8 and gif[0].shape == (24, 72, 3)                 # colour | depth | alpha
    r = imageio.get_reader(tmp_path / "rp" / "path.mp4")
    assert sum(1 for _ in r) == 8
    # frame 0 = the first training camera; rendered independently from gs_train's own PLY
    data = nerf_builtin(image_size=24, n_train=12, n_val=1, n_test=1, antialias=1, cache_dir=str(data_cache))
    model = GaussianModel(**load_gaussian_ply(run / "point_cloud.ply"))
    ref = rasterize_gaussians(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh, 0,
                              data.cameras[int(data.train[0])], data.background)["color"][0]
    err = np.abs(gif[0][:, :24] / 255.0 - ref.detach().clamp(0, 1).numpy())
    assert err.mean() < 2 / 255 and err.max() < 24 / 255, (err.mean() * 255, err.max() * 255)   # GIF palette
    assert json.loads((tmp_path / "rp" / "metrics.json").read_text())["source"] == "gs_train"
    used = read_camera_path(tmp_path / "rp" / "camera_path.json")
    torch.testing.assert_close(used.R[0], data.cameras.R[int(data.train[0])], atol=1e-5, rtol=0)
    # the PLY alone: an orbit about +Y around the splats
    rp = compose("task=render_path", f"ply={run / 'point_cloud.ply'}", "path=orbit", "num_frames=3",
                 "image_size=16", "formats=[gif]", "panels=[color,alpha]", "tensorboard=false", "sh_degree=0")
    run_task(rp, out_dir=tmp_path / "ply")
    assert imageio.mimread(tmp_path / "ply" / "path.gif")[0].shape == (16, 32, 3)
    with pytest.raises(UserError, match="no keyframes"):
        (tmp_path / "e.json").write_text(json.dumps({"render_width": 8, "render_height": 8, "camera_path": []}))
        run_task(compose("task=render_path", f"checkpoint={run}", "path=camera_path", f"camera_path={tmp_path / 'e.json'}",
                         "tensorboard=false"), out_dir=tmp_path / "bad")
    assert not (tmp_path / "bad" / "path.mp4").exists()


FIELD_RUN = ["gif_frames=0", "before_after=false", "time_budget=0"]
VOLSDF_RUN = [*FIELD_RUN, "iters=20", "eval_every=20", "supersample=1", "stages.sphere_init.steps=50", "stages.free_space.steps=0",
              "mesh_resolution=16", "+sampler.resolution=24"]


@pytest.mark.parametrize("task, extra", [
    ("train_nerf", [*FIELD_RUN, "iters=25", "eval_every=25", "batch_rays=512"]),
    ("volsdf", VOLSDF_RUN),
    ("volsdf", [*VOLSDF_RUN, "density=neus", "s=3.0", "density.mode=anneal", "density.s_end=100"]),  # the loaded s is the run's last
    ("volsdf", [*VOLSDF_RUN, "beta=0.33", "density.beta_end=0.01", "data.elevation_range=[-60,60]"]),  # density=auto picks NeuS
])
def test_render_path_of_a_field_run_reproduces_its_test_psnr(compose, tmp_path, task, extra, data_cache):
    """render_path of a train_nerf / volsdf run, along a camera_path.json holding the run's test camera,
    must give the test PSNR the task itself reported (the task's evaluation is the reference)."""
    from omegaconf import OmegaConf

    from l3d_app.data.nerf_views import nerf_builtin

    data_args = ["data.image_size=24", "data.n_train=12", "data.n_val=1", "data.n_test=1", "data.antialias=1",
                 f"data.cache_dir={data_cache}"]
    run = tmp_path / task
    cfg = compose(f"task={task}", *data_args, *extra, "tensorboard=false", "threads=1")
    run_task(cfg, out_dir=run)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    metrics = json.loads((run / "metrics.json").read_text())
    psnr_task = metrics["psnr"]
    if "data.elevation_range=[-60,60]" in extra:     # density=auto, cameras from -60 to 60 degrees: half below, NeuS
        assert metrics["density"] == "neus" and metrics["s_final"] == pytest.approx(100.0, rel=1e-3)
    data = nerf_builtin(image_size=24, n_train=12, n_val=1, n_test=1, antialias=1, cache_dir=str(data_cache),
                        elevation_range=tuple(cfg.data.elevation_range))
    test = int(data.test[0])
    write_camera_path(tmp_path / "test_cam.json", data.cameras[[test, test]])
    rp = compose("task=render_path", f"checkpoint={run}", "path=camera_path", f"camera_path={tmp_path / 'test_cam.json'}",
                 "formats=[gif]", "panels=[color]", "tensorboard=false", "threads=1")
    run_task(rp, out_dir=tmp_path / "rp")
    frame = imageio.mimread(tmp_path / "rp" / "path.gif")[0][..., :3] / 255.0
    mse = float(((torch.from_numpy(frame) - data.images[test].double()) ** 2).mean())
    psnr_path = -10 * math.log10(mse)
    assert psnr_task > 12.0                                   # the run learnt something to reproduce
    assert abs(psnr_path - psnr_task) < 0.5, (psnr_path, psnr_task)   # GIF palette quantisation only
