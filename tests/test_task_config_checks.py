"""tasks/common.py's config checks: a bad number is a UserError that names its key (one line,
exit 2 at the command line); good values pass."""

import pytest
from omegaconf import OmegaConf

from l3d_app.errors import UserError
from l3d_app.tasks.common import require_nonnegative, require_positive


@pytest.mark.parametrize("value", [-1, -0.5, "x", True, None])
def test_nonnegative_rejects_and_names_the_key(value):
    cfg = OmegaConf.create({"w_chamfer": 0.1, "w_edge": value})
    with pytest.raises(UserError, match="w_edge must be a number >= 0"):
        require_nonnegative(cfg, "w_chamfer", "w_edge")


def test_nonnegative_accepts_zero_and_positive_and_positive_rejects_zero():
    cfg = OmegaConf.create({"w_chamfer": 0, "w_edge": 0.01})
    require_nonnegative(cfg, "w_chamfer", "w_edge")
    with pytest.raises(UserError, match="w_chamfer must be a positive number"):
        require_positive(cfg, "w_chamfer")


@pytest.mark.parametrize("task, override, needle", [
    ("gs_train", "sh_degree=7", "sh_degree must be 0, 1, 2 or 3"),       # used to fail when the schedule reached degree 4
    ("gs_train", "tile_size=0", "tile_size must be a positive number"),   # used to end in ZeroDivisionError
    ("volsdf", "+losses.eikonal.points=-1", "the eikonal term's points must be an integer >= 0"),
    ("volsdf", "mesh_resolution=1", "mesh_resolution must be an integer >= 2"),  # used to fail after training
    ("volsdf", "stages.coarse_to_fine.every=-2", "coarse_to_fine every must be an integer >= 0"),
    ("volsdf", "stages.free_space.opacity=1.5", "free_space opacity must lie in"),
    ("volsdf", "stages.free_space.margin=-0.1", "free_space margin must be a number >= 0"),
    ("volsdf", "stages.free_space.w_front=-1", "free_space w_front must be a number >= 0"),
    ("volsdf", "losses.free_points.margin_beta=-1", "margin_beta must be a number >= 0"),
    ("volsdf", "losses.free_points.points=0", "the free-points term's points must be a positive integer"),
    ("volsdf", "losses.free_rays.weight=-0.1", "a loss term's weight must be a number >= 0"),
    ("volsdf", "+losses.free_rays.until=0", "until must lie after start"),
    ("volsdf", "losses.ncc.size=4", "the patch term's size must be odd"),
    ("volsdf", "+losses.ncc.sources=0", "the patch term's sources must be a positive integer"),
    ("volsdf", "+losses.ncc.best=5", "the patch term's best must be at most its sources"),
    ("volsdf", "losses.ncc.weight=-1", "a loss term's weight must be a number >= 0"),
    ("volsdf", "losses.ncc.until=-0.5", "until must be null or a number >= 0"),
    ("volsdf", "+losses.mask.typo=1", "unknown key 'typo' for loss term 'mask_bce'"),
    ("volsdf", "beta=-0.1", "beta must be > 0"),                           # used to blame beta_min, after the data
    ("volsdf", "density.beta_end=0", "beta_end must be > 0"),
    ("volsdf", "density.mode=foo", "density mode must be anneal, learnable or fixed"),
    ("volsdf", "density=neus s=-1", "s must be > 0"),
    ("volsdf", "density=neus density.mode=anneal density.s_end=0", "s mode anneal needs s_end > 0"),
])
def test_task_rejects_bad_values_before_loading_data(compose, task, override, needle):
    """Each check runs at the top of the task, before the data is read or a step is taken."""
    from l3d_app.registry import TASKS
    import l3d_app.tasks  # noqa: F401

    cfg = compose(f"task={task}", *override.split(), "data=blender", "data.root=/no/such/folder")
    with pytest.raises(UserError, match=needle):
        TASKS.get(task)(cfg, None)


@pytest.mark.parametrize("override, needle", [
    ("time_budget=-1", "time_budget must be a number >= 0"),
    ("turntable_size=-1", "turntable_size must be a number >= 0"),   # train_nerf used to fail after training
    ("fps=0", "fps must be a positive number"),
    ("eval_views=-1", "eval_views must be a number >= 0"),
])
def test_shared_run_keys_are_checked_before_the_task_starts(compose, tmp_path, override, needle):
    from l3d_app.app import run_task

    cfg = compose("task=train_nerf", override, "data=blender", "data.root=/no/such/folder")
    with pytest.raises(UserError, match=needle):
        run_task(cfg, out_dir=tmp_path)
    assert not list(tmp_path.glob("events.out.tfevents.*"))     # failed before the logger was made


@pytest.mark.parametrize("task, override, needle", [
    ("fit_mesh", "w_chamfer=-1", "w_chamfer must be a number >= 0"),       # used to train, maximising chamfer
    ("fit_mesh", "lr_final=-1", "lr_final must be a number >= 0"),
    ("train_nerf", "mesh_resolution=1", "mesh_resolution must be an integer >= 2"),   # with extract_mesh: after training
])
def test_fit_weights_and_nerf_mesh_resolution_are_checked_up_front(compose, task, override, needle):
    from l3d_app.registry import TASKS
    import l3d_app.tasks  # noqa: F401

    extra = ["extract_mesh=true", "data=blender", "data.root=/no/such/folder"] if task == "train_nerf" else []
    cfg = compose(f"task={task}", override, *extra)
    with pytest.raises(UserError, match=needle):
        TASKS.get(task)(cfg, None)


@pytest.mark.parametrize("task, override, needle", [
    ("neural_sdf", "w_offsurface=-1", "w_offsurface must be a number >= 0"),   # used to train, rewarding the loss
    ("neural_sdf", "init_radius=-1", "init_radius must be a positive number"),
    ("neural_sdf", "mesh_resolution=-1", "mesh_resolution must be an integer >= 2"),
    ("neural_sdf", "val_fraction=1.5", "val_fraction must be in"),
    ("sphere_trace", "inexact_step_scale=-1", "inexact_step_scale must be a positive number"),
])
def test_neural_sdf_and_sphere_trace_check_their_knobs(compose, task, override, needle):
    from l3d_app.registry import TASKS
    import l3d_app.tasks  # noqa: F401

    with pytest.raises(UserError, match=needle):
        TASKS.get(task)(compose(f"task={task}", override), None)


@pytest.mark.parametrize("override, needle", [
    ("eval_points=-1", "eval_points must be a positive number"),
    ("regulariser_weight=-1", "regulariser_weight must be a number >= 0"),    # used to train, rewarding it
    ("test_points=-1", "test_points must be a number >= 0"),
])
def test_pointnet_training_knobs_are_checked(compose, override, needle):
    from l3d_app.tasks.point_common import check_train_knobs

    with pytest.raises(UserError, match=needle):
        check_train_knobs(compose("task=pointnet_cls", override))


@pytest.mark.parametrize("override, needle", [
    ("init_noise=-0.1", "init_noise must be a number >= 0"),    # a standard deviation
    ("shift=-1", "shift must be a number >= 0"),                # a roll in pixels
])
def test_sds_image_rejects_negative_noise_and_shift(compose, override, needle):
    from l3d_app.registry import TASKS
    import l3d_app.tasks  # noqa: F401

    with pytest.raises(UserError, match=needle):
        TASKS.get("sds_image")(compose("task=sds_image", override), None)

