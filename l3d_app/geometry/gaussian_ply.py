"""3D Gaussians <-> the standard 3DGS PLY layout (binary little-endian float32 vertices).

Properties, in order: ``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2
rot_0..3``. As in the reference implementation, ``f_rest`` is stored channel-major
(all 15 coefficients of R, then G, then B), ``opacity`` is the logit, ``scale_*`` the log
standard deviations and ``rot_*`` the quaternion ``(w, x, y, z)``; normals are zeros.
Files with fewer ``f_rest`` (lower SH degree) load with the missing coefficients zero.

Plain tensors in and out (geometry does not know the model class):
``save_gaussian_ply(path, **model.tensors())`` and ``GaussianModel(**load_gaussian_ply(path))``
(:class:`~l3d_app.models.gaussians.GaussianModel`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Dict

import numpy as np
import torch

from l3d_app.errors import UserError
from l3d_app.runtime.files import atomic_path


def gaussian_ply_fields(n_rest: int = 45) -> list:
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                         "rot_0", "rot_1", "rot_2", "rot_3"])


def save_gaussian_ply(path: os.PathLike, means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                      opacity_logits: torch.Tensor, sh_dc: torch.Tensor, sh_rest: torch.Tensor) -> Path:
    """Write N Gaussians: means (N, 3), log_scales (N, 3) or (N, 1) (isotropic: written as
    three equal scales), quats (N, 4) ``(w, x, y, z)``, opacity_logits (N,), sh_dc (N, 1, 3),
    sh_rest (N, K-1, 3)."""
    with torch.no_grad():
        n = means.shape[0]
        f = lambda t: t.detach().float().cpu()  # noqa: E731
        rest = f(sh_rest).transpose(1, 2).reshape(n, -1)                                   # channel-major
        cols = [f(means), torch.zeros(n, 3), f(sh_dc).reshape(n, 3), rest, f(opacity_logits).reshape(n, 1),
                f(log_scales).expand(n, 3), f(quats)]
        data = torch.cat(cols, 1).numpy().astype("<f4")
    names = gaussian_ply_fields(rest.shape[1])
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
    header += "".join(f"property float {k}\n" for k in names) + "end_header\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(np.ascontiguousarray(data).tobytes())
    return Path(path)


def load_gaussian_ply(path: os.PathLike) -> Dict[str, torch.Tensor]:
    """Read a 3DGS PLY -> {means (N, 3), log_scales (N, 3), quats (N, 4), opacity_logits (N,),
    sh_dc (N, 1, 3), sh_rest (N, 15, 3)} float32 (SH padded to degree 3)."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise UserError(f"{path} is not a PLY file")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise UserError(f"{path}: only binary_little_endian Gaussian PLY files are supported")
    n = next((int(l.split()[2]) for l in header if l.startswith("element vertex")), None)
    props = [(l.split()[1], l.split()[2]) for l in header if l.startswith("property")]
    types = {"float": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4"}
    try:
        dtype = np.dtype([(name, types[t]) for t, name in props])
    except KeyError as err:
        raise UserError(f"{path}: unsupported property type {err}") from err
    if n is None:
        raise UserError(f"{path}: no 'element vertex' line in the header")
    if n == 0:
        raise UserError(f"{path} holds no Gaussians (element vertex 0)")
    body = raw[end + len(b"end_header\n"):]
    if len(body) < n * dtype.itemsize:
        raise UserError(f"{path}: file is truncated ({len(body)} bytes for {n} Gaussians of {dtype.itemsize})")
    v = np.frombuffer(body, dtype=dtype, count=n)
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [k for k in need if k not in dtype.names]
    if missing:
        raise UserError(f"{path}: not a 3DGS PLY, missing {missing}")
    col = lambda *k: torch.from_numpy(np.stack([v[x].astype(np.float32) for x in k], -1))  # noqa: E731
    bad = [k for k in need if not np.isfinite(v[k].astype(np.float64)).all()]
    if bad:
        raise UserError(f"{path}: non-finite values in {bad}")
    rest_names = sorted((k for k in dtype.names if re.fullmatch(r"f_rest_\d+", k)), key=lambda k: int(k[7:]))
    if len(rest_names) not in (0, 9, 24, 45):        # SH degree 0, 1, 2, 3: 3 x (K - 1) coefficients
        raise UserError(f"{path}: {len(rest_names)} f_rest properties; a 3DGS PLY has 0, 9, 24 or 45")
    per = len(rest_names) // 3
    rest = torch.zeros(n, 15, 3)
    if per:
        rest[:, :per] = col(*rest_names).reshape(n, 3, per).transpose(1, 2)
    return {"means": col("x", "y", "z"), "log_scales": col("scale_0", "scale_1", "scale_2"),
            "quats": col("rot_0", "rot_1", "rot_2", "rot_3"), "opacity_logits": col("opacity")[:, 0],
            "sh_dc": col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :], "sh_rest": rest}
