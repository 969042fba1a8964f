"""Validation PSNR and render seconds of a finished volsdf run re-rendered with other sample counts.

    python bench/volsdf_eval_samples.py RUN_DIR [--counts 128/16 128/32 256/32] [--views 4] [--threads 2]
                                        [--supersample 1 2] [--set density.quadrature=linear ...]

Each ``C/F`` renders the run's first ``--views`` validation views (0: all) at each ``--supersample``
factor (s x s rays per pixel, averaged, as volsdf's test views; default one ray per pixel) with
``sampler.n_coarse=C`` and ``sampler.n_fine=F`` (the evaluation counts ``sampler.eval_n_coarse`` /
``sampler.eval_n_fine`` set in a run apply the same way), from the run's checkpoint, with the cache
refreshed from the final field as volsdf's own evaluation does; ``--set KEY=VALUE`` changes other entries of
the run's config first (values parsed as YAML). Prints one line per count: the mean
PSNR over the views (dB), the PSNR and SSIM as volsdf's evaluation scores them (one MSE over all views,
clamped renders) and the wall seconds of the render. Validation views only: what it finds
may choose a setting; test views are not read.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--counts", nargs="+", default=["128/16", "128/32", "256/32"])
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--supersample", nargs="+", type=int, default=[1], help="rays per pixel side, averaged")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config entries to change first")
    args = ap.parse_args()
    import l3d_app.models  # noqa: F401  (registries)
    import l3d_app.render  # noqa: F401
    from omegaconf import OmegaConf
    from l3d_app.registry import DATASETS
    from l3d_app.tasks.field_common import evaluate_views
    from l3d_app.tasks.render_path import volsdf_rays

    torch.set_num_threads(args.threads)
    cfg_file, ckpt = args.run / ".hydra" / "config.yaml", args.run / "checkpoint.pt"
    if not cfg_file.is_file() or not ckpt.is_file():
        raise SystemExit(f"{args.run}: not a finished run (needs .hydra/config.yaml and checkpoint.pt)")
    state = torch.load(ckpt, map_location="cpu", weights_only=False)["trainable"]
    for spec in args.counts:
        try:
            n_coarse, n_fine = (int(x) for x in spec.split("/"))
        except ValueError:
            raise SystemExit(f"--counts takes COARSE/FINE pairs such as 128/16, got {spec!r}")
        conf = OmegaConf.load(cfg_file)
        if str(conf.get("task_name")) != "volsdf":
            raise SystemExit(f"{args.run}: a {conf.get('task_name')} run, not volsdf")
        for item in args.set:
            key, sep, value = item.partition("=")
            if not sep or not key:
                raise SystemExit(f"--set takes KEY=VALUE, got {item!r}")
            OmegaConf.update(conf, key, yaml.safe_load(value), force_add=True)
        conf.sampler.n_coarse, conf.sampler.n_fine = n_coarse, n_fine
        conf.sampler.eval_n_coarse, conf.sampler.eval_n_fine = n_coarse, n_fine
        data = DATASETS.build(conf.data)
        rays = volsdf_rays(conf, state, data, torch.device("cpu"))
        views = data.val[: args.views] if args.views > 0 else data.val
        for factor in args.supersample:
            t0 = time.perf_counter()
            with torch.no_grad():
                scores, _, out = evaluate_views(rays, data.cameras[views], data.images[views], 4096, factor)
            seconds = time.perf_counter() - t0
            truth = data.images[views]
            mse = ((out["color"].reshape(truth.shape) - truth) ** 2).mean(dim=(1, 2, 3))
            print(f"{args.run.name} {n_coarse}/{n_fine} {factor}x{factor}{' ' + ' '.join(args.set) if args.set else ''}: "
                  f"val {float((-10 * torch.log10(mse)).mean()):.2f} dB (mean over views); as volsdf scores it "
                  f"{scores['psnr']:.3f} dB, SSIM {scores['ssim']:.4f}; {len(views)} views, {seconds:.1f} s", flush=True)


if __name__ == "__main__":
    main()
