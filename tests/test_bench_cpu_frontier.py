"""bench/bench_cpu_frontier.py's three training paths, small: in fp32 eager each matches the bench's own
float64 reference to float32 rounding (so the bench's accuracy columns measure bf16/compile, not the
harness), and bf16 autocast differs from it by more than fp32 does (the variant is really applied)."""

import argparse

import pytest

from bench_scripts import load_bench_script


def _args():
    return argparse.Namespace(nerf_rays=64, nerf_samples=8, sdf_rays=32, sdf_samples=8, sdf_eik=32,
                              gaussians=200, size=24, warmup=1, repeats=1, vary_rays=False)


@pytest.mark.parametrize("path", ["nerf", "sdf", "gauss"])
def test_fp32_path_matches_the_float64_reference_and_bf16_does_not(path):
    bench = load_bench_script("bench_cpu_frontier")
    rows = {r["variant"]: r for r in bench.bench_path(path, _args(), ["fp32", "bf16"])}
    fp32, bf16 = rows["fp32"], rows["bf16"]
    assert fp32["finite"] and bf16["finite"]
    assert fp32["out_max"] < 1e-5 and fp32["grad_relmean"] < 1e-4
    assert bf16["out_max"] > 10 * fp32["out_max"]
