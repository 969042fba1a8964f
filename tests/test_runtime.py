import json
import os

import numpy as np
import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.runtime.device import resolve_device
from l3d_app.runtime.files import atomic_path, write_json
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.media import save_gif, to_uint8
from l3d_app.runtime.seed import seed_everything


def test_resolve_device():
    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(UserError):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(UserError):
            resolve_device("cuda")


def test_seed_reproducible():
    a = torch.rand(5, generator=seed_everything(3))
    b = torch.rand(5, generator=seed_everything(3))
    assert torch.equal(a, b)


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert os.listdir(tmp_path) == []
    write_json(target, {"psnr": np.float32(30.5), "n": torch.tensor(3)})
    assert json.loads(target.read_text()) == {"n": 3, "psnr": 30.5}
    assert os.listdir(tmp_path) == ["out.json"]


def test_to_uint8_clamps_and_rounds():
    out = to_uint8(np.array([-1.0, 0.0, 0.5, 1.0, 2.0]))
    assert out.tolist() == [0, 0, 128, 255, 255]


def test_gif_roundtrip(tmp_path):
    import imageio.v2 as imageio

    frames = torch.rand(3, 8, 10, 3)
    path = save_gif(tmp_path / "a.gif", frames, fps=10)
    back = np.stack(imageio.mimread(path))
    assert back.shape[:3] == (3, 8, 10)


def test_gif_bytes_are_the_file_and_keep_few_colours_exactly(tmp_path):
    """Four colours (a GIF palette holds them exactly): decoded frames equal the uint8 input; the
    in-memory bytes are the file's bytes."""
    import imageio.v2 as imageio

    from l3d_app.runtime.media import gif_bytes
    palette = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    frames = palette[torch.arange(2 * 6 * 5).reshape(2, 6, 5) % 4]
    frames[1] = frames[1].flip(0)
    data = gif_bytes(frames, fps=10)
    assert save_gif(tmp_path / "b.gif", frames, fps=10).read_bytes() == data
    back = np.stack(imageio.mimread(data, format="GIF"))[..., :3]
    assert np.array_equal(back, to_uint8(frames))


def _events(log_dir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(log_dir), size_guidance={"tensors": 0, "scalars": 0, "images": 0})
    acc.Reload()
    return acc


def test_logger_writes_scalars_images_hparams_in_one_run(tmp_path):
    log = RunLogger(tmp_path)
    log.log_scalars({"loss": 1.5}, step=0)
    log.log_scalars({"loss": 0.5}, step=1)
    log.image_sequence("frames", torch.rand(3, 4, 4, 3))
    log.text("note", "hello")
    log.hparams({"beta": 0.1, "task": "volsdf", "shape": [1, 2]}, {"psnr": 25.0, "bad": float("nan")})
    log.close()
    # hparams go into the same event file: no extra timestamped sub-run folder
    assert [p for p in tmp_path.iterdir() if p.is_dir()] == []
    acc = _events(tmp_path)
    assert [e.value for e in acc.Scalars("loss")] == [1.5, 0.5]
    assert len(acc.Images("frames")) == 3
    assert acc.Scalars("final/psnr")[0].value == 25.0
    assert "final/bad" not in acc.Tags()["scalars"]
    plugins = acc.PluginTagToContent("hparams")
    assert "_hparams_/experiment" in plugins and "_hparams_/session_start_info" in plugins
