"""l3d_app entry point: ``python main.py task=<name> key=value ...`` (Hydra)."""

import hydra
from omegaconf import DictConfig


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig):
    from l3d_app.app import run

    return run(cfg)


if __name__ == "__main__":
    main()
