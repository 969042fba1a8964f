"""sds_mesh and its pieces: the texture field, the field-textured renderer, the checker scores, tiny runs."""

from __future__ import annotations

import pytest
import torch

from l3d_app.data.scenes import builtin_scene
from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable
from l3d_app.geometry.mesh import Mesh
from l3d_app.render.mesh.renderer import MeshRenderer
from l3d_app.metrics.prompt_match import score_frames
from l3d_app.models.texture_field import TextureField
from l3d_app.render.mesh.field_texture import FieldTextureRenderer
from conftest import course_data
from sds_task_runs import numbers_finite, run_metrics

SMALL = ("iters=3", "eval_every=3", "eval_views=2", "num_frames=2", "batch_views=2", "batch_frames=2",
         "turntable_size=32", "tensorboard=false", "threads=1")


class _Linear(torch.nn.Module):
    """rgb = 0.5 + 0.25 p: linear in the point, so vertex interpolation of it is exact."""

    def __init__(self):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.tensor(0.25))

    def forward(self, p):
        return 0.5 + self.scale * p


@pytest.mark.parametrize("shading", ["unlit", "lambert"])
def test_field_texture_equals_vertex_colours_for_a_linear_field(shading):
    mesh = builtin_scene("icosphere", normalize=True)
    cams = turntable(3, 3.0, 20.0, 40.0, 24)
    field = _Linear()
    kw = dict(shading=shading, background=(1.0, 1.0, 1.0))
    got = FieldTextureRenderer(field, **kw)(mesh, cams)
    coloured = Mesh(verts=mesh.verts, faces=mesh.faces, vert_colors=(0.5 + 0.25 * mesh.verts))
    ref = MeshRenderer(**kw)(coloured, cams)
    assert torch.allclose(got["image"], ref["image"], atol=1e-5)
    got["image"].sum().backward()                 # differentiable w.r.t. the field's parameters
    assert torch.isfinite(field.scale.grad) and float(field.scale.grad.abs()) > 0


def test_texture_field_starts_grey_and_trains():
    field = TextureField(n_frequencies=3, hidden=16, layers=2)
    p = torch.randn(50, 3)
    assert torch.allclose(field(p), torch.full((50, 3), 0.5))
    mesh = builtin_scene("cube", normalize=True)
    img = FieldTextureRenderer(field, shading="unlit")(mesh, turntable(2, 3.0, 10.0, 40.0, 16))["image"]
    ((img - torch.tensor([0.9, 0.1, 0.1])) ** 2).mean().backward()
    grads = [q.grad for q in field.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert float(sum(g.abs().sum() for g in grads)) > 0


def test_scores_of_known_images():
    img = torch.ones(2, 32, 32, 3)
    img[0, 8:24, 8:24] = torch.tensor([0.9, 0.1, 0.1])         # a red square on white
    img[1, 8:24, 8:24] = torch.tensor([0.1, 0.2, 0.9])         # a blue square on white
    s = score_frames(img, "a red square on white")
    assert s == {"match": 0.5, "colour_ok": 0.5, "shape_ok": 1.0, "background_ok": 1.0}
    assert all(v is None for v in score_frames(img, "a cow wearing a hat").values())   # no verdict


def _run(compose, tmp_path, *overrides):
    return run_metrics(compose, tmp_path, "task=sds_mesh", *SMALL, *overrides)



def test_sds_mesh_tiny_run_writes_outputs_with_finite_metrics(compose, tmp_path):
    m = _run(compose, tmp_path)
    assert (tmp_path / "sds_mesh.gif").exists() and (tmp_path / "after.png").exists()
    assert m["iters"] == 3 and m["image_size"] == 32 and numbers_finite(m)
    for key in ("match_rate", "match_rate_before", "colour_match_rate", "seconds", "seconds_per_iter", "n_params"):
        assert key in m
    assert m["match_rate_before"] == 0.0        # the grey start is no red square


def test_sds_mesh_raises_the_prompt_match_from_its_grey_start(compose, tmp_path):
    """The shipped built-in prior paints the cube in 30 steps (seed 0, chosen for this test):
    the checker's match over the turntable rises from the grey start's 0 to most frames, and
    the colour is the prompt's on every frame. A broken texture gradient stays grey."""
    m = _run(compose, tmp_path, "iters=30", "eval_every=30", "num_frames=4", "batch_frames=4", "seed=0")
    assert m["match_rate_before"] == 0.0
    assert m["match_rate"] >= 0.75 and m["colour_match_rate"] == 1.0, m


def test_sds_mesh_on_the_course_cow(compose, tmp_path):
    cow = course_data("cow", "cow.obj")
    m = _run(compose, tmp_path, "data=mesh", f"data.path={cow}", "iters=2", "prompt=a blue square on white")
    assert m["iters"] == 2 and numbers_finite(m)


def test_sds_mesh_needs_a_mesh_and_a_readable_prompt(compose, tmp_path):
    with pytest.raises(UserError):   # the built-in prior's vocabulary
        _run(compose, tmp_path, "prompt=a cow wearing a hat")
    with pytest.raises(UserError):
        _run(compose, tmp_path, "batch_views=0")


def test_sds_mesh_interrupt_and_resume_equals_an_uninterrupted_run(compose, tmp_path, monkeypatch):
    from l3d_app.app import RunInterrupted

    whole, parts = tmp_path / "whole", tmp_path / "parts"
    _run(compose, whole, "iters=4")
    monkeypatch.setenv("L3D_STOP_AT_STEP", "2")
    with pytest.raises(RunInterrupted):
        _run(compose, parts, "iters=4")
    monkeypatch.delenv("L3D_STOP_AT_STEP")
    m = _run(compose, parts, "iters=4", "resume=true")
    assert m["iters"] == 4
    a, b = (torch.load(d / "checkpoint.pt", weights_only=False)["trainable"]["modules"]["texture"]
            for d in (whole, parts))
    assert all(torch.equal(a[k], b[k]) for k in a)
