"""Benchmark: the CPU frontier of the three hot paths -- fp32, bf16 autocast, torch.compile --
speed against error. Run by hand, never in tests:

    python bench/bench_cpu_frontier.py [--threads 1] [--repeats 7] [--paths nerf,sdf,gauss]
        [--variants fp32,bf16,compile,compile+bf16] [--autotune] [--out docs/cpu_frontier.md]

Hot paths (forward + backward of one training step's field / rasteriser work, the library
functions as they are):

* ``nerf``: :class:`~l3d_app.models.nerf.GridField` (train_nerf's default ``model=grid_field``)
  on ``--nerf-rays`` x ``--nerf-samples`` points, composited along the rays
  (:func:`~l3d_app.render.volume.renderer.composite`), L2 colour loss; backward to every parameter.
* ``sdf``: :class:`~l3d_app.models.sdf_grid.SDFGridField` (volsdf's default) ``sdf_rgb_grad``
  (SDF, colour and the exact spatial gradient) on ``--sdf-rays`` x ``--sdf-samples`` fine
  samples, VolSDF optical depth at beta 0.01 + composite, L2 colour loss, plus the eikonal loss
  on the same gradients and on ``--sdf-eik`` extra points; backward to every parameter.
* ``gauss``: :func:`~l3d_app.render.gaussians.rasterize.rasterize_gaussians` of ``--gaussians`` splats
  (SH degree 3, isotropic scales from the point density, opacity 0.1-0.6) into one
  ``--size`` x ``--size`` view (tile 4, gs_train's default), L1 loss; backward to every parameter.

The grids' tables are filled with uniform values in +-0.5 (nerf) / +-0.05 (sdf), as after some
training (at their near-zero initialisation, bf16's error would look smaller than it is).

Variants: ``fp32`` (eager), ``bf16`` (``torch.autocast("cpu", dtype=torch.bfloat16)`` around
the forward and loss, :func:`l3d_app.runtime.precision.autocast`), ``compile``
(``torch.compile`` of the forward + loss; the backward is compiled by AOTAutograd), and
``compile+bf16``; ``--autotune`` adds the same two with ``mode="max-autotune-no-cudagraphs"``;
``compile-dyn`` compiles with ``dynamic=True`` (one kernel for every point count; with
``--vary-rays`` the nerf repeats use a random ray count each, as occupancy skipping gives).
All variants of one path run in the same process on the same module and inputs, ROUND-ROBIN
(repeat r of every variant before repeat r + 1 of any), so the load of the shared machine falls
on all of them alike; the first ``--warmup`` calls of each variant (compilation included) are
excluded and the first call's seconds are reported as ``first call``.

Accuracy: outputs (rendered colours) and all parameter gradients of every variant against the
same step in float64 (the module and inputs copied to double, eager): max and mean absolute
error of the outputs; for the gradients, max |error| / max |reference| and mean |error| /
mean |reference| over all parameters concatenated. The fp32 row is the floor every variant is
compared with.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from l3d_app.geometry.cameras import look_at_cameras  # noqa: E402
from l3d_app.losses.eikonal import eikonal_loss  # noqa: E402
from l3d_app.models.nerf import GridField  # noqa: E402
from l3d_app.models.sdf_grid import SDFGridField  # noqa: E402
from l3d_app.render.gaussians.rasterize import rasterize_gaussians  # noqa: E402
from l3d_app.render.sdf.densities import volsdf_density  # noqa: E402
from l3d_app.render.volume.renderer import composite  # noqa: E402
from l3d_app.runtime.precision import autocast, maybe_compile  # noqa: E402

BOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))

# A path's step: step(params, inputs) -> (loss, output) with the module closed over.
Step = Callable[..., Tuple[torch.Tensor, torch.Tensor]]


def _rays(n: int, g: torch.Generator) -> Tuple[torch.Tensor, torch.Tensor]:
    """n rays from a sphere of radius 3 towards points near the origin: origins, unit dirs (n, 3)."""
    o = torch.randn(n, 3, generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    d = torch.randn(n, 3, generator=g) * 0.3 - o
    return o, d / d.norm(dim=-1, keepdim=True)


# ---------------------------------------------------------------------------------- hot paths
def nerf_path(args) -> Tuple[torch.nn.Module, Dict[str, torch.Tensor], Callable]:
    g = torch.Generator().manual_seed(0)
    field = GridField(scene_box=BOX)
    with torch.no_grad():
        field.encoding.table.copy_((torch.rand(field.encoding.table.shape, generator=g) - 0.5))
    R, S = args.nerf_rays, args.nerf_samples
    o, d = _rays(R, g)
    t = 1.5 + 3.0 * (torch.arange(S) + torch.rand(R, S, generator=g)) / S                  # (R, S) sorted
    inputs = {"pts": (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3), "t": t,
              "target": torch.rand(R, 3, generator=g)}

    def step(field, pts, t, target):
        sigma, rgb = field(pts)
        out = composite(rgb.reshape(*t.shape, 3).float(), t, sigmas=sigma.reshape(t.shape).float())["color"]
        return ((out - target) ** 2).mean(), out

    return field, inputs, step


def sdf_path(args) -> Tuple[torch.nn.Module, Dict[str, torch.Tensor], Callable]:
    g = torch.Generator().manual_seed(1)
    field = SDFGridField(scene_box=BOX)
    with torch.no_grad():
        field.encoding.table.copy_((torch.rand(field.encoding.table.shape, generator=g) - 0.5) * 0.1)
    R, S = args.sdf_rays, args.sdf_samples
    o, d = _rays(R, g)
    # fine samples cluster around the init sphere (radius 0.85) as after importance sampling
    hit = 3.0 - 0.85
    t = hit + 0.3 * (torch.arange(S) + torch.rand(R, S, generator=g)) / S - 0.15
    pts = (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)
    eik = (torch.rand(args.sdf_eik, 3, generator=g) * 2 - 1) * 1.5
    inputs = {"pts": pts, "dirs": d[:, None].expand(R, S, 3).reshape(-1, 3), "eik": eik, "t": t,
              "far": torch.full((R,), 4.5), "target": torch.rand(R, 3, generator=g)}

    def step(field, pts, dirs, eik, t, far, target):
        f, rgb, grad = field.sdf_rgb_grad(pts, dirs)
        seg = torch.diff(torch.cat([t, far[:, None]], dim=1), dim=1)           # sample i to i+1, the last to far
        tau = volsdf_density(f.reshape(t.shape).float(), 100.0, 0.01) * seg    # VolSDF, alpha 100, beta 0.01
        out = composite(rgb.reshape(*t.shape, 3).float(), t, sigmas=tau, deltas=torch.ones_like(t))["color"]
        g_eik = field.sdf_features_gradient(eik)[2]
        loss = ((out - target) ** 2).mean() + 0.1 * eikonal_loss(torch.cat([grad, g_eik]).float())
        return loss, out

    return field, inputs, step


class _Splats(torch.nn.Module):
    """The rasteriser's parameters as one module (so the bench treats all paths alike)."""

    def __init__(self, n: int, g: torch.Generator):
        super().__init__()
        means = (torch.rand(n, 3, generator=g) * 2 - 1)
        spacing = (8.0 / n) ** (1.0 / 3.0)                      # mean distance in the [-1, 1]^3 box
        self.means = torch.nn.Parameter(means)
        self.log_scales = torch.nn.Parameter(torch.full((n, 3), math.log(0.5 * spacing))
                                             + 0.3 * torch.randn(n, 3, generator=g))
        self.quats = torch.nn.Parameter(torch.randn(n, 4, generator=g))
        self.opacity_logits = torch.nn.Parameter(torch.logit(0.1 + 0.5 * torch.rand(n, generator=g)))
        self.sh = torch.nn.Parameter(0.2 * torch.randn(n, 16, 3, generator=g))


def gauss_path(args) -> Tuple[torch.nn.Module, Dict[str, torch.Tensor], Callable]:
    g = torch.Generator().manual_seed(2)
    splats = _Splats(args.gaussians, g)
    cams = look_at_cameras(3.0, 20.0, 30.0, 50.0, args.size)
    inputs = {"target": torch.rand(args.size, args.size, 3, generator=g)}

    def step(splats, target):
        out = rasterize_gaussians(splats.means, splats.log_scales, splats.quats, splats.opacity_logits, splats.sh,
                                  3, cams, tile_size=4)["color"][0]
        return (out.float() - target).abs().mean(), out

    return splats, inputs, step


PATHS = {"nerf": nerf_path, "sdf": sdf_path, "gauss": gauss_path}


# ---------------------------------------------------------------------------------- variants
def make_variant(module: torch.nn.Module, step: Callable, precision: str, compile_kw) -> Callable:
    """A callable ``(**inputs) -> (loss, output)`` running ``step`` under ``precision``, compiled
    with ``torch.compile(**compile_kw)`` unless ``compile_kw`` is None."""

    def forward(**inputs):
        with autocast(precision, "cpu"):
            return step(module, **inputs)

    if compile_kw is None:
        return forward
    return maybe_compile(forward, True, **compile_kw)


def parse_variant(name: str):
    """``fp32`` | ``bf16`` | ``compile[+bf16]`` | ``compile-dyn[+bf16]`` (``dynamic=True``) |
    ``autotune[+bf16]`` -> (precision, torch.compile keyword arguments or None)."""
    precision = "bf16" if name.endswith("+bf16") or name == "bf16" else "fp32"
    head = name.split("+")[0]
    kinds = {"fp32": None, "bf16": None, "compile": {}, "compile-dyn": {"dynamic": True},
             "autotune": {"mode": "max-autotune-no-cudagraphs"}}
    if head not in kinds:
        raise SystemExit(f"unknown variant {name!r}; known: {', '.join(kinds)} (each optionally +bf16)")
    return precision, kinds[head]


def _grads(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1).double()
                      for p in module.parameters()])


def run_once(fn: Callable, module: torch.nn.Module, inputs: Dict[str, torch.Tensor]):
    """One forward + backward; (wall s, cpu s, output float64, grads float64)."""
    module.zero_grad(set_to_none=True)
    t0, c0 = time.perf_counter(), time.process_time()
    loss, out = fn(**inputs)
    loss.backward()
    return time.perf_counter() - t0, time.process_time() - c0, out.detach().double(), _grads(module)


def accuracy(out, grads, ref_out, ref_grads) -> Dict[str, float]:
    d_out, d_g = (out - ref_out).abs(), (grads - ref_grads).abs()
    finite = bool(torch.isfinite(out).all() and torch.isfinite(grads).all())
    return {"out_max": float(d_out.max()), "out_mean": float(d_out.mean()),
            "grad_relmax": float(d_g.max() / ref_grads.abs().max().clamp_min(1e-300)),
            "grad_relmean": float(d_g.mean() / ref_grads.abs().mean().clamp_min(1e-300)), "finite": finite}


def bench_path(name: str, args, variants: List[str]) -> List[dict]:
    module, inputs, step = PATHS[name](args)
    # float64 reference: the same module and inputs in double, eager, no autocast
    m64 = copy.deepcopy(module).double()
    in64 = {k: v.double() for k, v in inputs.items()}
    _, _, ref_out, ref_grads = run_once(lambda **kw: step(m64, **kw), m64, in64)
    fns = {v: make_variant(module, step, *parse_variant(v)) for v in variants}
    rows = {v: {"variant": v, "wall": [], "cpu": []} for v in variants}
    for v in variants:                                  # warm-up (and compilation): excluded
        for i in range(args.warmup):
            wall, cpu, out, grads = run_once(fns[v], module, inputs)
            if i == 0:
                rows[v]["first_call_s"] = wall
                rows[v].update(accuracy(out, grads, ref_out, ref_grads))
                rows[v]["fell_back"] = bool(getattr(fns[v], "failed", False))
        print(f"  {name}/{v}: warm-up done, first call {rows[v]['first_call_s']:.2f} s", flush=True)
    g = torch.Generator().manual_seed(123)
    for _ in range(args.repeats):                       # round-robin
        batch = inputs
        if args.vary_rays and name == "nerf":           # a different ray count each repeat (as occupancy skipping gives)
            batch = _fewer_rays(inputs, int(torch.randint(args.nerf_rays // 2, args.nerf_rays + 1, (1,), generator=g)))
        for v in variants:
            wall, cpu, _, _ = run_once(fns[v], module, batch)
            rows[v]["wall"].append(wall)
            rows[v]["cpu"].append(cpu)
    out = []
    for v in variants:
        r = rows[v]
        w = sorted(r.pop("wall"))
        c = sorted(r.pop("cpu"))
        r.update(path=name, wall_median=statistics.median(w), wall_min=w[0], wall_max=w[-1],
                 cpu_median=statistics.median(c))
        out.append(r)
    base = out[0]["cpu_median"]
    for r in out:
        r["speedup_cpu"] = base / r["cpu_median"]
    return out


def _fewer_rays(inputs: Dict[str, torch.Tensor], r: int) -> Dict[str, torch.Tensor]:
    """The nerf path's inputs restricted to the first r rays."""
    S = inputs["t"].shape[1]
    return {"pts": inputs["pts"][: r * S], "t": inputs["t"][:r], "target": inputs["target"][:r]}


def matmul_probe(n: int = 65536, k: int = 128, repeats: int = 10) -> Dict[str, float]:
    """Milliseconds of one bare (n, k) @ (k, k) matmul in fp32 and in bf16 (the median of
    ``repeats`` after two warm-ups) at the current thread count: whether this CPU has native bf16
    matrix instructions (AMX, AVX512-BF16), which the hot paths' timings alone do not show."""
    g = torch.Generator().manual_seed(0)
    x, w = torch.randn(n, k, generator=g), torch.randn(k, k, generator=g)
    out = {}
    for name, dt in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        a, b = x.to(dt), w.to(dt)
        times = []
        for i in range(repeats + 2):
            t0 = time.perf_counter()
            a @ b
            if i >= 2:
                times.append(time.perf_counter() - t0)
        out[f"matmul_{name}_ms"] = 1e3 * statistics.median(times)
    return out


def machine_line() -> str:
    """CPU capability as torch sees it, and the bare-matmul probe."""
    m = matmul_probe()
    return (f"torch CPU capability {torch.backends.cpu.get_cpu_capability()}; bare 65536x128 @ 128x128 matmul "
            f"fp32 {m['matmul_fp32_ms']:.2f} ms, bf16 {m['matmul_bf16_ms']:.2f} ms "
            f"({m['matmul_fp32_ms'] / m['matmul_bf16_ms']:.1f}x)")


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "load: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def describe(name: str, args) -> str:
    return {"nerf": f"grid_field, {args.nerf_rays} rays x {args.nerf_samples} samples "
                    f"= {args.nerf_rays * args.nerf_samples} points",
            "sdf": f"sdf_grid_field + grad, {args.sdf_rays} x {args.sdf_samples} fine + {args.sdf_eik} eikonal points",
            "gauss": f"rasterize_gaussians, {args.gaussians} splats, {args.size}x{args.size}, SH 3"}[name]


def write_markdown(path: Path, rows: List[dict], args, load_before: str, load_after: str, seconds: float,
                   cmd: str, machine: str = "") -> None:
    lines = ["| path | variant | median wall s (min-max) | median CPU s | speed-up (CPU) | first call s | "
             "out max err | out mean err | grad rel max err | grad rel mean err |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        flag = " (fell back to eager)" if r.get("fell_back") else ""
        fin = "" if r["finite"] else " NON-FINITE"
        lines.append(f"| {r['path']} | {r['variant']}{flag} | {r['wall_median']:.3f} ({r['wall_min']:.3f}-"
                     f"{r['wall_max']:.3f}) | {r['cpu_median']:.3f} | {r['speedup_cpu']:.2f}x | "
                     f"{r['first_call_s']:.1f} | {r['out_max']:.2e}{fin} | {r['out_mean']:.2e} | "
                     f"{r['grad_relmax']:.2e} | {r['grad_relmean']:.2e} |")
    table = "\n".join(lines)
    text = (f"<!-- generated by bench/bench_cpu_frontier.py -->\n"
            f"Command: `{cmd}`\n\n"
            f"torch {torch.__version__}, threads={torch.get_num_threads()}, repeats={args.repeats} "
            f"(round-robin), warm-up {args.warmup} per variant, {seconds:.0f} s in all.\n\n"
            f"Load before: `{load_before}`  \nLoad after: `{load_after}`\n\n"
            + (f"Machine: {machine}\n\n" if machine else "")
            + "\n".join(f"- {p}: {describe(p, args)}" for p in args.paths.split(",")) + "\n\n" + table + "\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    begin, end = "<!-- bench:begin -->", "<!-- bench:end -->"
    old = path.read_text() if path.exists() else ""
    if begin in old and end in old:                     # a page with prose around the table: replace the table
        text = old[:old.index(begin) + len(begin)] + "\n" + text + old[old.index(end):]
    path.write_text(text)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--paths", default="nerf,sdf,gauss")
    p.add_argument("--variants", default="fp32,bf16,compile,compile+bf16")
    p.add_argument("--autotune", action="store_true", help="add autotune, autotune+bf16 (max-autotune-no-cudagraphs)")
    p.add_argument("--nerf-rays", type=int, default=2048)
    p.add_argument("--nerf-samples", type=int, default=32)
    p.add_argument("--sdf-rays", type=int, default=1024)
    p.add_argument("--sdf-samples", type=int, default=16)
    p.add_argument("--sdf-eik", type=int, default=1024)
    p.add_argument("--gaussians", type=int, default=20000)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--vary-rays", action="store_true",
                   help="nerf: each timed repeat uses a random ray count in [rays/2, rays] (recompilation cost)")
    p.add_argument("--json", default="", help="also save the rows as JSON after each path")
    p.add_argument("--out", default="", help="markdown file for the table (e.g. docs/cpu_frontier_table.md)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    variants = args.variants.split(",") + (["autotune", "autotune+bf16"] if args.autotune else [])
    load_before, t0 = _uptime(), time.perf_counter()
    machine = machine_line()
    print(f"threads={torch.get_num_threads()}  {load_before}\n{machine}", flush=True)
    rows = []
    for name in args.paths.split(","):
        print(f"{name}: {describe(name, args)}", flush=True)
        rows += bench_path(name, args, variants)
        _print_rows(rows)
        if args.json:                                   # saved path by path: a long run keeps what it has
            Path(args.json).write_text(json.dumps({"rows": rows, "load_before": load_before, "machine": machine,
                                                   "load_now": _uptime(), "threads": args.threads}, indent=1))
    load_after = _uptime()
    print(f"{load_after}")
    _print_rows(rows)
    if args.out:
        cmd = "python bench/bench_cpu_frontier.py " + " ".join(sys.argv[1:] if argv is None else argv)
        write_markdown(REPO / args.out, rows, args, load_before, load_after, time.perf_counter() - t0, cmd, machine)
        print(f"wrote {args.out}")


def _print_rows(rows: List[dict]) -> None:
    hdr = f"{'path':6s} {'variant':14s} {'wall med':>9s} {'min':>7s} {'max':>7s} {'cpu med':>8s} {'x':>5s} " \
          f"{'first':>6s} {'out max':>9s} {'out mean':>9s} {'g relmax':>9s} {'g relmean':>9s}"
    print(hdr)
    for r in rows:
        print(f"{r['path']:6s} {r['variant']:14s} {r['wall_median']:9.3f} {r['wall_min']:7.3f} {r['wall_max']:7.3f} "
              f"{r['cpu_median']:8.3f} {r['speedup_cpu']:5.2f} {r['first_call_s']:6.1f} {r['out_max']:9.2e} "
              f"{r['out_mean']:9.2e} {r['grad_relmax']:9.2e} {r['grad_relmean']:9.2e}"
              + ("" if r["finite"] else " NON-FINITE") + (" FELL-BACK" if r.get("fell_back") else ""), flush=True)


if __name__ == "__main__":
    main()
