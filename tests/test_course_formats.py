"""The course's own formats, each on small files written here in that exact layout:
rgbd_data.pkl (pickled PyTorch3D cameras, read without PyTorch3D), tiny_nerf_data.npz, and the
neural-rendering assignment's <scene>.pth + <scene>.png (PyTorch3D NeRF layout)."""

import pickle
import sys
import types

import numpy as np
import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras, to_opengl_c2w, to_pytorch3d
from l3d_app.geometry.primitives import icosphere
from l3d_app.geometry.point_mesh_distance import point_mesh_distance
from l3d_app.render.mesh.rgbd import rgbd_from_mesh

S = 24


def _fake_pytorch3d():
    """Install stand-in pytorch3d modules so pickles name pytorch3d.renderer.cameras.* classes."""
    mods = {n: types.ModuleType(n) for n in ("pytorch3d", "pytorch3d.renderer", "pytorch3d.renderer.cameras")}

    class PerspectiveCameras:
        def __init__(self, **kw):
            self.__dict__.update(kw)

    PerspectiveCameras.__module__ = "pytorch3d.renderer.cameras"
    PerspectiveCameras.__qualname__ = "PerspectiveCameras"
    mods["pytorch3d.renderer.cameras"].PerspectiveCameras = PerspectiveCameras
    return mods, PerspectiveCameras


def write_rgbd_pkl(path, mesh, scale_R=1.0):
    cams = look_at_cameras(3.0, torch.tensor([20.0, -10.0]), torch.tensor([30.0, 200.0]), 50.0, S)
    views = rgbd_from_mesh(mesh, cams)
    R, T, focal, pp = to_pytorch3d(cams)
    mods, P3 = _fake_pytorch3d()
    saved = {k: sys.modules.get(k) for k in mods}
    sys.modules.update(mods)
    try:
        data = {}
        for k in (1, 2):
            data[f"rgb{k}"] = views["rgb"][k - 1].numpy()
            data[f"depth{k}"] = views["depth"][k - 1].numpy()
            data[f"mask{k}"] = views["mask"][k - 1].float().numpy()
            data[f"cameras{k}"] = P3(R=R[k - 1:k] * (scale_R if k == 2 else 1.0), T=T[k - 1:k], focal_length=focal[k - 1:k],
                                     principal_point=pp[k - 1:k], _in_ndc=True, device=torch.device("cpu"), _N=1)
        with open(path, "wb") as f:
            pickle.dump(data, f)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    return data, R.double().numpy(), T.double().numpy(), focal.double().numpy(), pp.double().numpy()


def course_unproject(depth, mask, R, T, f, p):
    """The course's unproject_depth_image, re-derived in float64 NumPy: NDC grid
    linspace(1, -1, S), X_view = (x - px) Z / fx, X_world = (X_view - T) R^T."""
    n = depth.shape[0]
    g = np.linspace(1, -1, n)
    Y, X = np.meshgrid(g, g, indexing="ij")
    Z = depth.astype(np.float64)
    view = np.stack([(X - p[0]) * Z / f[0], (Y - p[1]) * Z / f[1], Z], -1)
    world = (view - T) @ R.T
    return world[mask > 0.5]


def test_rgbd_pickle_reproduces_the_course_clouds_and_the_union(tmp_path):
    from l3d_app.data.course_rgbd import course_rgbd

    mesh = icosphere(3, 0.8)
    mesh = type(mesh)(verts=mesh.verts, faces=mesh.faces, vert_colors=(mesh.verts * 0.5 + 0.5).clamp(0, 1))
    data, R, T, f, p = write_rgbd_pkl(tmp_path / "rgbd_data.pkl", mesh)
    assert "pytorch3d" not in sys.modules
    clouds = {}
    for k in (1, 2):
        c = course_rgbd(str(tmp_path / "rgbd_data.pkl"), view=str(k))
        ref = course_unproject(data[f"depth{k}"], data[f"mask{k}"], R[k - 1], T[k - 1], f[k - 1], p[k - 1])
        np.testing.assert_allclose(c.points.numpy(), ref, atol=1e-5)
        np.testing.assert_allclose(c.colors.numpy(), data[f"rgb{k}"][data[f"mask{k}"] > 0.5], atol=1e-6)
        clouds[k] = c
    u = course_rgbd(str(tmp_path / "rgbd_data.pkl"), view="union")
    assert u.num_points == clouds[1].num_points + clouds[2].num_points > 100
    # the exact pixel-centre cloud lies on the surface; the course grid is off by up to ~a pixel
    exact = course_rgbd(str(tmp_path / "rgbd_data.pkl"), view="union", course_grid=False)
    d_exact = point_mesh_distance(exact.points, mesh)[0]
    d_course = point_mesh_distance(u.points, mesh)[0]
    assert float(d_exact.max()) < 0.02 and float(d_course.mean()) > 2 * float(d_exact.mean())


def test_rgbd_pickle_refuses_other_classes_and_bad_views(tmp_path):
    from l3d_app.data.course_rgbd import course_rgbd

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    with open(tmp_path / "bad.pkl", "wb") as f:
        pickle.dump({"rgb1": Evil()}, f)
    with pytest.raises(UserError, match="refusing to load builtins.print"):
        course_rgbd(str(tmp_path / "bad.pkl"))
    with open(tmp_path / "short.pkl", "wb") as f:
        pickle.dump({"rgb1": np.zeros((4, 4, 3))}, f)
    with pytest.raises(UserError, match="no 'depth1' entry"):
        course_rgbd(str(tmp_path / "short.pkl"), view="1")
    with pytest.raises(UserError, match="view must be 1, 2 or union"):
        course_rgbd(str(tmp_path / "short.pkl"), view="3")
    write_rgbd_pkl(tmp_path / "scaled.pkl", icosphere(1, 0.8), scale_R=1.2)
    with pytest.raises(UserError, match=r"scaled.pkl: cameras2: camera: camera rotation is not rigid"):
        course_rgbd(str(tmp_path / "scaled.pkl"))


def test_tiny_nerf_npz(tmp_path):
    from l3d_app.data.course_nerf import tiny_nerf

    cams = look_at_cameras(4.0, 30.0, torch.arange(12) * 30.0, 40.0, 10)
    c2w = to_opengl_c2w(cams).numpy()
    imgs = np.random.default_rng(0).random((12, 10, 10, 3)).astype(np.float32)
    np.savez(tmp_path / "tiny_nerf_data.npz", images=imgs, poses=c2w, focal=np.array(float(cams.fx[0])))
    d = tiny_nerf(str(tmp_path / "tiny_nerf_data.npz"), n_train=9, val_every=4)
    assert d.test.tolist() == [9, 10, 11] and d.val.tolist() == [3, 7] and len(d.train) == 7
    torch.testing.assert_close(d.cameras.R, cams.R, atol=1e-5, rtol=0)
    torch.testing.assert_close(d.cameras.t, cams.t, atol=1e-5, rtol=0)
    torch.testing.assert_close(d.images, torch.from_numpy(imgs))
    assert d.up.tolist() == [0.0, 0.0, 1.0]
    c2w[5, 0, 0] = np.nan
    np.savez(tmp_path / "bad.npz", images=imgs, poses=c2w, focal=np.array(30.0))
    with pytest.raises(UserError, match="bad.npz: frame 5: camera pose has a non-finite"):
        tiny_nerf(str(tmp_path / "bad.npz"))


def test_course_lego_pth_png_layout(tmp_path):
    import imageio.v2 as imageio

    from l3d_app.data.course_nerf import course_lego

    n, h = 6, 16
    cams = look_at_cameras(4.0, 20.0, torch.arange(n) * 60.0, 40.0, h)
    R, T, focal, pp = to_pytorch3d(cams)
    pp = pp + torch.tensor([0.05, -0.03])                              # off-centre principal point
    torch.save({"cameras": {"R": R, "T": T, "focal_length": focal, "principal_point": pp},
                "split": [[0, 1, 2, 3], [4], [5]]}, tmp_path / "materials.pth")
    imgs = np.random.default_rng(0).integers(0, 256, (n, h, h, 3)).astype(np.uint8)
    imageio.imwrite(tmp_path / "materials.png", imgs.reshape(n * h, h, 3))
    d = course_lego(str(tmp_path), scene="materials")
    assert d.train.tolist() == [0, 1, 2, 3] and d.val.tolist() == [4] and d.test.tolist() == [5]
    torch.testing.assert_close(d.images, torch.from_numpy(imgs / 255.0).float())
    # a world point projects where PyTorch3D's NDC formula puts it (independent float64 check)
    X = torch.tensor([[0.3, -0.2, 0.1]], dtype=torch.float64)
    uv, _ = d.cameras.to(dtype=torch.float64).project(X)
    v = X @ R.double() + T.double()[:, None]                         # (n, 1, 3) PyTorch3D view
    ndc = focal.double()[:, None] * v[..., :2] / v[..., 2:] + pp.double()[:, None]
    u_ref = h / 2 - ndc[..., 0] * h / 2                               # NDC +X left, +Y up; pixel edges
    v_ref = h / 2 - ndc[..., 1] * h / 2
    torch.testing.assert_close(uv[..., 0], u_ref, atol=1e-4, rtol=0)
    torch.testing.assert_close(uv[..., 1], v_ref, atol=1e-4, rtol=0)
    half = course_lego(str(tmp_path), scene="materials", image_size=[8, 8])
    assert half.image_size == (8, 8)
    torch.testing.assert_close(half.cameras.fx, d.cameras.fx / 2)
