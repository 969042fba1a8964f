"""Visibility culling of extracted meshes (l3d_app.render.mesh.visibility): what no camera
sees is removed, what some camera sees is kept, by area against the analytic shares."""

import pytest
import torch

from l3d_app.geometry import primitives as P
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.render.mesh.visibility import cull_unseen_faces, seen_faces


def _cams(elevations, n_azim=12):
    el = torch.tensor(elevations, dtype=torch.float32).repeat_interleave(n_azim)
    az = (torch.arange(n_azim) * 360.0 / n_azim).repeat(len(elevations))
    return look_at_cameras(4.0, el, az, 40.0, 48)


def test_a_box_seen_from_above_loses_its_bottom_and_what_is_inside_it():
    outer, inner = P.cube(1.0), P.cube(0.3)          # the inner box is a leftover no camera sees
    mesh = P.join([outer, inner])
    keep = seen_faces(mesh, _cams([30.0, 60.0]), tolerance=0.02)
    normals = mesh.face_normals()
    is_outer = torch.arange(mesh.num_faces) < outer.num_faces
    bottom = normals[:, 1] < -0.9                     # +Y is up for look_at_cameras
    assert keep.tolist() == (is_outer & ~bottom).tolist()
    culled, removed = cull_unseen_faces(mesh, _cams([30.0, 60.0]), tolerance=0.02)
    # analytic share of the area: the outer bottom (1 of 6 unit faces) + the whole inner box
    expected = (1.0 + 6 * 0.3 ** 2) / (6.0 + 6 * 0.3 ** 2)
    assert removed == pytest.approx(expected, abs=1e-6)
    assert culled.num_faces == 10 and culled.num_verts == 8


def test_a_sphere_seen_from_all_round_keeps_every_face_and_bad_tolerance_is_refused():
    sphere = P.icosphere(3, 1.0)
    culled, removed = cull_unseen_faces(sphere, _cams([-60.0, -20.0, 20.0, 60.0]), tolerance=0.02)
    assert removed == 0.0 and culled.num_faces == sphere.num_faces
    # from above only: a convex surface point is seen by a camera at C iff n . C > |p| = 1
    # (the tangent-cone condition); faces clearly on either side of it are kept / culled
    cams = _cams([20.0, 60.0])
    keep = seen_faces(sphere, cams, tolerance=0.02)
    n, centres = sphere.face_normals().double(), cams.centers().double()
    reach = (n @ centres.T).max(dim=1).values                                 # max over cameras of n . C
    assert not keep[reach < 0.95].any()
    assert 0.05 < float((reach < 0.95).double().mean()) < 0.5                     # a real lower cap is culled
    # every face some camera sees at less than 75 degrees from its normal is kept; only
    # grazing faces at the edge of the seen cap may go (the depth lookup is ambiguous there)
    to_cam = centres[None] - sphere.face_verts().mean(1).double()[:, None]     # (F, B, 3)
    cos = ((n[:, None] * to_cam).sum(-1) / to_cam.norm(dim=-1)).max(dim=1).values
    assert keep[cos > 0.26].all() and float(keep[reach > 1.05].double().mean()) > 0.97
    with pytest.raises(ValueError):
        seen_faces(sphere, _cams([30.0]), tolerance=0.0)
