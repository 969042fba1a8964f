"""A marching-cubes grid that cannot fit the host memory is refused before training, in one line,
instead of an allocation failure after it. The memory available is faked, so the figures are arithmetic."""

import os

import pytest

from l3d_app.errors import UserError
from l3d_app.geometry.marching_cubes import GRID_BYTES_PER_POINT, require_grid_memory
from l3d_app.runtime.device import available_host_memory

GIB = 2 ** 30


def test_the_grid_needs_its_points_times_the_bytes_per_point():
    need = GRID_BYTES_PER_POINT * 512 ** 3                 # 17 x 134,217,728 bytes = 2.125 GiB
    require_grid_memory(512, need)                        # exactly enough: accepted
    with pytest.raises(UserError, match=r"mesh_resolution=512 needs about 2\.1 GiB .* 2\.1 GiB are available"):
        require_grid_memory(512, need - 1)
    require_grid_memory(4096, None)                       # memory not known: nothing refused


@pytest.mark.skipif(not os.path.exists("/proc/meminfo"), reason="MemAvailable is Linux's")
def test_the_machine_reports_its_available_memory():
    available = available_host_memory()
    physical = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")     # total RAM, read another way
    assert isinstance(available, int) and 0 < available <= physical


@pytest.mark.parametrize("task", [("task=volsdf",), ("task=train_nerf", "extract_mesh=true"), ("task=neural_sdf",)])
def test_a_task_refuses_a_grid_too_large_before_its_data(compose, tmp_path, monkeypatch, task):
    from l3d_app import registry
    from l3d_app.app import run_task
    from l3d_app.tasks import common

    def no_work(*_, **__):
        raise AssertionError("the data was built before mesh_resolution was checked")
    monkeypatch.setattr(registry.DATASETS, "build", no_work)
    monkeypatch.setattr(common, "available_host_memory", lambda: 1 * GIB)
    with pytest.raises(UserError, match="mesh_resolution=512 needs about 2.1 GiB of memory"):
        run_task(compose(*task, "mesh_resolution=512", "tensorboard=false"), out_dir=tmp_path / "run")
    assert not [p for p in (tmp_path / "run").rglob("*") if p.is_file()]
    common.require_mesh_resolution(compose(*task, "mesh_resolution=256"))     # 0.27 GiB: fits
