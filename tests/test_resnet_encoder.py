"""encoder=resnet18 for svr_train: the ResNet-18 architecture (torchvision's names and parameter count),
weights from a local file (and the one-line errors for a missing or mismatched one), svr_eval's reload."""

from __future__ import annotations

import json

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.errors import UserError
from l3d_app.models.image_encoders import build_image_encoder
from l3d_app.models.resnet_encoder import ResNet18Encoder, load_resnet18_weights

# torchvision's resnet18 has 11,689,512 parameters; its classifier fc (512 x 1000 + 1000) is not kept
RESNET18_TRUNK_PARAMS = 11_689_512 - 513_000


def test_resnet18_architecture():
    enc = ResNet18Encoder(64)
    assert sum(p.numel() for p in enc.parameters()) == RESNET18_TRUNK_PARAMS
    names = set(enc.state_dict())
    for key in ("conv1.weight", "bn1.running_var", "layer1.0.conv2.weight", "layer2.0.downsample.0.weight",
                "layer2.0.downsample.1.num_batches_tracked", "layer4.1.bn2.bias"):
        assert key in names
    assert len([k for k in names if k.endswith(".weight") and "conv" in k]) == 1 + 16
    enc.eval()
    for size in (32, 64):
        assert enc(torch.rand(2, size, size, 3)).shape == (2, 512)
    with pytest.raises(UserError, match="at least 32"):
        build_image_encoder(16, name="resnet18")
    with pytest.raises(UserError, match="Known: cnn, resnet18"):
        build_image_encoder(32, name="vgg")


def test_weights_from_a_local_file_and_clear_errors(tmp_path):
    torch.manual_seed(0)
    src = ResNet18Encoder(32)
    with torch.no_grad():                                        # non-trivial running statistics
        for m in src.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    state = {f"module.{k}": v for k, v in src.state_dict().items()}
    state.update({"module.fc.weight": torch.zeros(1000, 512), "module.fc.bias": torch.zeros(1000)})
    torch.save({"state_dict": state}, tmp_path / "r18.pth")
    dst = ResNet18Encoder(32)
    assert load_resnet18_weights(dst, tmp_path / "r18.pth") == len(src.state_dict())
    x = torch.rand(3, 32, 32, 3)
    torch.testing.assert_close(dst.eval()(x), src.eval()(x), rtol=0, atol=0)
    with pytest.raises(UserError, match="encoder weights not found"):
        load_resnet18_weights(dst, tmp_path / "none.pth")
    bad = dict(src.state_dict())
    bad["layer1.0.conv1.weight"] = torch.zeros(64, 64, 1, 1)
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(UserError, match=r"does not match ResNet-18 \(torchvision layout\): layer1.0.conv1.weight is \(64, 64, 1, 1\)"):
        load_resnet18_weights(dst, tmp_path / "bad.pth")
    torch.save({"conv1.weight": torch.zeros(64, 3, 7, 7)}, tmp_path / "part.pth")
    with pytest.raises(UserError, match="missing"):
        load_resnet18_weights(dst, tmp_path / "part.pth")
    (tmp_path / "text.pth").write_text("not a torch file")
    with pytest.raises(UserError, match="not a readable ResNet-18 state dict"):
        load_resnet18_weights(dst, tmp_path / "text.pth")


def _tiny(cache, *extra):
    return ("task=svr_train", "encoder=resnet18", "tensorboard=false", "image_size=32", f"data.cache_dir={cache}",
            "data.train_per_class=2", "data.test_per_class=1", "data.voxel_size=16", "data.num_points=256",
            "data.occupancy_points=256", "data.depth_views=3", "batch_size=4", "iters=2", "eval_every=0",
            "eval_points=64", "num_vis=1", "turntable_size=24", "num_frames=2", "vis_points=64", "vis_gif=false",
            "decoder=point", "decoder.num_points=64", "decoder.hidden=[32]", "decoder.target_points=64", "eval_at_end=false",
            *extra)


def test_svr_train_resnet18_from_a_file_and_its_model_file_reloads(compose, tmp_path):
    torch.manual_seed(1)
    torch.save(ResNet18Encoder(32).state_dict(), tmp_path / "r18.pth")
    with pytest.raises(UserError, match="encoder weights not found"):
        run_task(compose(*_tiny(tmp_path / "cache", f"encoder_weights={tmp_path / 'missing.pth'}")),
                 out_dir=tmp_path / "bad")
    with pytest.raises(UserError, match="encoder=resnet18 only"):
        run_task(compose(*_tiny(tmp_path / "cache", "encoder=cnn", f"encoder_weights={tmp_path / 'r18.pth'}")),
                 out_dir=tmp_path / "bad2")
    run_task(compose(*_tiny(tmp_path / "cache", f"encoder.weights={tmp_path / 'r18.pth'}")), out_dir=tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["n_params"] > RESNET18_TRUNK_PARAMS and m["iters"] == 2
    from l3d_app.models.svr_model import load_svr_model

    model, meta = load_svr_model(tmp_path / "run", "cpu")               # the weights file is not needed to reload
    assert meta["encoder_cfg"] == {"name": "resnet18"} and isinstance(model.encoder, ResNet18Encoder)
    start = torch.load(tmp_path / "r18.pth")
    moved = [k for k, v in model.encoder.state_dict().items() if not torch.equal(v, start[k])]
    assert moved and "conv1.weight" in moved                              # trained from the file's weights
