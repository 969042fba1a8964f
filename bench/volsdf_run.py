"""A finished volsdf run's SDF field on a bench scene: shared by the bench diagnosis scripts."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Iterable, Tuple


def run_scene_parser(doc: str) -> argparse.ArgumentParser:
    """An argument parser for a script over one finished volsdf run: ``run`` (its folder), ``scene`` (the
    bench scene's folder with its true ``mesh.ply``) and ``--threads`` (2); the description is ``doc``'s
    first paragraph."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--threads", type=int, default=2)
    return ap


def load_sdf_field(run: Path, scene: Path, also_needs: Iterable[str] = ()) -> Tuple[object, object, object]:
    """(config, data, model): ``run``'s Hydra config, the NeRF-synthetic scene at ``scene`` (with its
    true ``mesh.ply``) and the run's SDF field in eval mode with its checkpointed weights. Exits with
    one line where ``run`` lacks ``checkpoint.pt``, its config or any file of ``also_needs``, or the
    scene lacks ``mesh.ply``."""
    import torch
    import l3d_app.models  # noqa: F401  (registries)
    from omegaconf import OmegaConf
    from l3d_app.data.nerf_formats import blender
    from l3d_app.registry import MODELS

    for f in ("checkpoint.pt", ".hydra/config.yaml", *also_needs):
        if not (run / f).is_file():
            raise SystemExit(f"{run}: no {f} (a finished volsdf run is needed)")
    if not (scene / "mesh.ply").is_file():
        raise SystemExit(f"{scene}: no mesh.ply (a bench scene with its true mesh is needed)")
    conf = OmegaConf.load(run / ".hydra" / "config.yaml")
    state = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)["trainable"]
    data = blender(root=str(scene), mesh_path="mesh.ply")
    model = MODELS.build(conf.model, scene_box=data.scene_box.tolist()).eval()
    model.load_state_dict(state["modules"]["field"])
    return conf, data, model
