"""The built-in SVR dataset: determinism, shapes, cache, inside test, depth maps."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from l3d_app.data import svr_shapes as S
from l3d_app.errors import UserError
from l3d_app.geometry.voxels import voxelize_mesh, winding_number

TINY = dict(train_per_class=2, test_per_class=1, views_per_object=2, image_size=16, voxel_size=16,
            num_points=256, occupancy_points=256, depth_views=3)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    cache = tmp_path_factory.mktemp("svr_cache")
    return S.svr_shapes(cache_dir=str(cache), **TINY), cache


def test_shapes_and_splits(tiny):
    data, _ = tiny
    N = 3 * 3
    assert data.images.shape == (N, 2, 16, 16, 3)
    assert data.points.shape == (N, 256, 3) and data.voxels.shape == (N, 16, 16, 16)
    assert data.voxels.dtype == torch.bool and data.occ_labels.shape == (N, 256)
    assert data.depth.shape == (N, 3, 16, 16)
    # val carved from the 2 training objects of each class (one each), test untouched
    assert sorted(data.train.tolist() + data.val.tolist()) == [0, 1, 3, 4, 6, 7] and data.test.tolist() == [2, 5, 8]
    assert sorted(data.labels[data.val].tolist()) == [0, 1, 2] and len(data.train) == 3
    assert data.labels.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    # canonical frame: inside the unit sphere, farthest vertex at 1, images in [0, 1]
    assert float(data.verts.norm(dim=-1).max()) == pytest.approx(1.0, abs=1e-5)
    assert float(data.points.norm(dim=-1).max()) <= 1.0 + 1e-5
    assert 0.0 <= float(data.images.min()) and float(data.images.max()) <= 1.0
    assert int(data.voxels.flatten(1).any(1).sum()) >= N - 2  # (thin lamps may miss every 16^3 cell centre)
    for i in range(N):  # every object is visible and has an inside
        assert bool(data.occ_labels[i].any())
        assert bool((data.depth[i] > 0).any()) and float(data.images[i].min()) < 0.9
        assert data.mesh(i).faces.max() < data.mesh(i).num_verts


def test_deterministic_and_cached(tiny, tmp_path):
    data, cache = tiny
    files = list(cache.glob("svr_shapes_*.pt"))
    assert len(files) == 1
    again = S.svr_shapes(cache_dir=str(cache), **TINY)            # from the cache
    fresh = S.svr_shapes(cache_dir=str(tmp_path), **TINY)         # regenerated elsewhere
    for other in (again, fresh):
        assert torch.equal(other.images, data.images) and torch.equal(other.voxels, data.voxels)
        assert torch.equal(other.points, data.points) and torch.equal(other.depth, data.depth)
    different = S.svr_shapes(cache_dir=str(tmp_path), **{**TINY, "seed": 1})
    assert not torch.equal(different.points, data.points)
    assert len(list(tmp_path.glob("svr_shapes_*.pt"))) == 2


def test_depth_maps_match_the_mesh(tiny):
    """Unprojected depth pixels lie on the mesh surface ."""
    from l3d_app.geometry.point_mesh_distance import point_mesh_distance
    from l3d_app.geometry.rgbd import unproject_depth

    data, _ = tiny
    cloud = unproject_depth(data.depth[0], data.depth_cameras)
    d = point_mesh_distance(cloud.points, data.mesh(0))[0]
    assert cloud.num_points > 10 and float(d.max()) < 1e-4


@pytest.mark.parametrize("category", S.CLASS_NAMES)
def test_convex_union_inside_matches_winding_number(category):
    rng = np.random.default_rng([5, S.CLASS_NAMES.index(category)])
    mesh, parts = S.make_object(category, rng)
    pts = torch.rand(3000, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    ours = S.inside_convex_union(parts, pts)
    ref = winding_number(mesh, pts.double(), dtype=torch.float64) > 0.5
    assert bool(ours.any()) and torch.equal(ours, ref)
    assert torch.equal(S.inside_convex_union(parts, torch.zeros(0, 3)), torch.zeros(0, dtype=torch.bool))


def test_voxels_match_voxelize_mesh():
    mesh, parts = S.make_object("table", np.random.default_rng(3))
    from l3d_app.geometry.voxels import voxel_centers

    ours = S.inside_convex_union(parts, voxel_centers(12, S.BOUNDS).reshape(-1, 3)).reshape(12, 12, 12)
    assert torch.equal(ours, voxelize_mesh(mesh, 12, S.BOUNDS))


def test_frustum_is_closed_and_outward():
    m = S.frustum(0.4, 0.1, 0.5, 16)
    w = winding_number(m, torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.24, 0.0], [0.3, 0.2, 0.0], [0.0, 1.0, 0.0]]))
    assert w.tolist() == pytest.approx([1.0, 1.0, 0.0, 0.0], abs=1e-4)


def test_bad_knobs(tmp_path):
    with pytest.raises(UserError, match="unknown svr_shapes class"):
        S.svr_shapes(classes=["sofa"], cache_dir=str(tmp_path))
    with pytest.raises(UserError, match="image_size"):
        S.svr_shapes(image_size=4, cache_dir=str(tmp_path))
    with pytest.raises(UserError, match="test_per_class"):
        S.svr_shapes(test_per_class=0, cache_dir=str(tmp_path))
