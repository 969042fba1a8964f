"""The single-view-reconstruction model: image encoder + decoder, and its self-contained file.

``svr_model.pt`` holds the weights and everything that rebuilds the model (encoder and
decoder configs, the data geometry) plus whatever ``meta`` the caller adds (svr_train adds
the data config, so svr_eval evaluates on the same test split without any other knob).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, Tuple

import torch
from torch import nn

from l3d_app.errors import UserError
from l3d_app.models import svr_decoders, svr_pseudo  # noqa: F401  (register the decoders)
from l3d_app.models.image_encoders import build_image_encoder
from l3d_app.registry import MODELS
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.torch_files import read_torch_file

MODEL_FILE = "svr_model.pt"


class SVRModel(nn.Module):
    """Image encoder + decoder: ``model(images)`` is the (B, latent_dim) feature the decoder
    reads (``model.decoder.points(feature, ...)``, ``model.decoder.shapes(feature)``)."""

    def __init__(self, encoder: nn.Module, decoder: nn.Module):
        super().__init__()
        self.encoder, self.decoder = encoder, decoder

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) -> (B, latent_dim) features."""
        return self.encoder(images)


def build_svr_model(encoder_cfg: Dict, decoder_cfg: Dict, geometry: Dict) -> SVRModel:
    """Encoder at ``geometry["image_size"]`` with ``encoder_cfg`` (its ``name``: cnn or resnet18; without one
    the CNN); the decoder registered as
    ``decoder_cfg["name"]`` with the rest of ``decoder_cfg`` and the data ``geometry``."""
    encoder = build_image_encoder(int(geometry["image_size"]), **encoder_cfg)
    decoder = MODELS.build(decoder_cfg, latent_dim=encoder.latent_dim, geometry=geometry)
    return SVRModel(encoder, decoder)


def save_svr_model(path: Path, model: SVRModel, meta: Dict[str, Any]) -> None:
    """Write weights + ``meta`` (must hold encoder_cfg, decoder_cfg, geometry) atomically."""
    for key in ("encoder_cfg", "decoder_cfg", "geometry"):
        if key not in meta:
            raise ValueError(f"svr model meta needs {key!r}")
    with atomic_path(Path(path)) as tmp:
        torch.save({"state": model.state_dict(), **meta}, tmp)


def load_svr_model(path, device) -> Tuple[SVRModel, Dict[str, Any]]:
    """Rebuild the model of a ``svr_model.pt`` (or of a run folder holding one); returns
    (model in eval mode on ``device``, meta without the weights)."""
    if path is None or str(path) == "":
        raise UserError(f"svr_eval needs checkpoint=PATH: a {MODEL_FILE} or the svr_train run folder holding it")
    p = Path(str(path)).expanduser()
    if p.is_dir():
        p = p / MODEL_FILE
    if not p.is_file():
        raise UserError(f"svr model checkpoint not found: {p} (train one with task=svr_train)")
    meta = read_torch_file(p, "svr model checkpoint")
    if not isinstance(meta, dict) or "decoder_cfg" not in meta:
        raise UserError(f"{p} is not an svr_train model file ({MODEL_FILE})")
    model = build_svr_model(meta["encoder_cfg"], meta["decoder_cfg"], meta["geometry"])
    model.load_state_dict(meta.pop("state"))
    return model.to(device).eval(), meta


def n_params(model: nn.Module) -> int:
    """Number of parameters."""
    return sum(p.numel() for p in model.parameters())
