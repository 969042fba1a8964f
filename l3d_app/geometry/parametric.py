"""Parametric surfaces sampled as point clouds (torus, superquadric).

Sampling: the parameters are drawn **i.i.d. uniform in the parameter rectangle** (random, not
a grid), from the caller's ``torch.Generator`` — so ``num_samples`` can be any integer and a
run is reproducible from its seed. Uniform in the parameters is NOT uniform in area: on the
torus, points crowd the inner equator (the area element is ``r (R + r cos v) du dv``); on a
superquadric they crowd the poles and, for small exponents, the edges. ``torus_points`` offers
``area_uniform=True`` (exact area-uniform samples by rejection) for references and metrics.

Points are returned with unit normals and colours ``0.5 + 0.5 * normal`` (the direction of the
surface shows as colour). Axes as in :mod:`l3d_app.geometry.sdf`: +Y up, the torus's axis and
the superquadric's polar axis are Y.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.runtime.config_values import config_floats


def _check_count(num_samples: int) -> int:
    if int(num_samples) != num_samples or num_samples <= 0:
        raise UserError(f"num_samples must be a positive integer, got {num_samples!r}")
    return int(num_samples)


def _uniform(n: int, lo: float, hi: float, generator, dtype) -> torch.Tensor:
    dev = generator.device if generator is not None else "cpu"
    return lo + (hi - lo) * torch.rand(n, generator=generator, dtype=dtype, device=dev)


def _cloud(points: torch.Tensor, normals: torch.Tensor, device) -> PointCloud:
    normals = torch.nn.functional.normalize(normals, dim=-1, eps=1e-20)
    colors = (0.5 + 0.5 * normals).clamp(0, 1)
    return PointCloud(points, colors, normals).to(device=device)


def signed_power(x: torch.Tensor, exponent: float) -> torch.Tensor:
    """``sign(x) |x|^exponent`` (elementwise), the superquadric's signed power."""
    return torch.sign(x) * x.abs().pow(exponent)


def torus_points(num_samples: int, major_radius: float = 0.7, minor_radius: float = 0.3,
                 generator: Optional[torch.Generator] = None, area_uniform: bool = False,
                 device=None, dtype: torch.dtype = torch.float32) -> PointCloud:
    """``num_samples`` points on the torus around the Y axis (R = major, r = minor radius).

    Parameterisation, u, v in [0, 2 pi)::

        x = (R + r cos v) cos u,   y = r sin v,   z = (R + r cos v) sin u
        normal = (cos v cos u, sin v, cos v sin u)

    ``area_uniform=False``: (u, v) uniform in the parameters (denser on the inner side).
    ``area_uniform=True``: exact area-uniform points: v is accepted with probability
    ``(R + r cos v) / (R + r)`` (the area element's v-dependence; rejection sampling in batches).

    Returns a PointCloud with points (N, 3) (world units), normals and colours, on ``device``
    (default: the generator's device) in ``dtype``.
    """
    n = _check_count(num_samples)
    R = float(major_radius)
    r = float(minor_radius)
    if not (R > 0 and r > 0):
        raise UserError(f"torus radii must be positive, got major={R}, minor={r}")
    u = _uniform(n, 0.0, 2 * math.pi, generator, dtype)
    if area_uniform:
        v = _area_uniform_v(n, R, r, generator, dtype)
    else:
        v = _uniform(n, 0.0, 2 * math.pi, generator, dtype)
    cu, su, cv, sv = u.cos(), u.sin(), v.cos(), v.sin()
    ring = R + r * cv
    points = torch.stack([ring * cu, r * sv, ring * su], dim=-1)
    normals = torch.stack([cv * cu, sv, cv * su], dim=-1)
    return _cloud(points, normals, device if device is not None else points.device)


def _area_uniform_v(n: int, R: float, r: float, generator, dtype) -> torch.Tensor:
    """n angles v with density proportional to (R + r cos v) on [0, 2 pi) (rejection sampling)."""
    accept_rate = R / (R + r)  # mean of (R + r cos v) / (R + r)
    out, have = [], 0
    while have < n:
        m = int((n - have) / accept_rate * 1.1) + 16
        v = _uniform(m, 0.0, 2 * math.pi, generator, dtype)
        w = _uniform(m, 0.0, 1.0, generator, dtype)
        keep = v[w * (R + r) <= R + r * v.cos()]
        out.append(keep)
        have += keep.numel()
    return torch.cat(out)[:n]


def superquadric_points(num_samples: int, radii: Sequence[float] = (0.8, 0.8, 0.8),
                        exponents: Sequence[float] = (0.5, 0.5),
                        generator: Optional[torch.Generator] = None,
                        device=None, dtype: torch.dtype = torch.float32) -> PointCloud:
    """``num_samples`` points on the superellipsoid (semi-axes ``radii`` = (a, b, c) along X, Y,
    Z; ``exponents`` = (e1, e2); polar axis Y), signed-power parameterisation (Barr 1981)::

        eta in [-pi/2, pi/2] (latitude), omega in [-pi, pi) (longitude), spow(t, e) = sign(t)|t|^e
        x = a spow(cos eta, e1) spow(cos omega, e2)
        y = b spow(sin eta, e1)
        z = c spow(cos eta, e1) spow(sin omega, e2)

    These satisfy ``F(p) = (|x/a|^(2/e2) + |z/c|^(2/e2))^(e2/e1) + |y/b|^(2/e1) = 1`` exactly
    (see :class:`l3d_app.geometry.sdf.Superquadric`). (eta, omega) are uniform in the parameters
    (crowding at the poles). Normals are the gradient direction of F::

        n ~ (spow(cos eta, 2-e1) spow(cos omega, 2-e2) / a, spow(sin eta, 2-e1) / b,
             spow(cos eta, 2-e1) spow(sin omega, 2-e2) / c)

    Returns a PointCloud (N, 3) with normals and colours ``0.5 + 0.5 n``.
    """
    n = _check_count(num_samples)
    a, b, c = config_floats(radii, "radii", 3)
    e1, e2 = config_floats(exponents, "exponents", 2)
    if not (a > 0 and b > 0 and c > 0):
        raise UserError(f"superquadric radii must be positive, got {list(radii)}")
    if not (0 < e1 <= 4 and 0 < e2 <= 4):
        raise UserError(f"superquadric exponents must be in (0, 4], got {list(exponents)}")
    eta = _uniform(n, -math.pi / 2, math.pi / 2, generator, dtype)
    omega = _uniform(n, -math.pi, math.pi, generator, dtype)
    ce, se, co, so = eta.cos(), eta.sin(), omega.cos(), omega.sin()
    points = torch.stack([a * signed_power(ce, e1) * signed_power(co, e2),
                          b * signed_power(se, e1),
                          c * signed_power(ce, e1) * signed_power(so, e2)], dim=-1)
    normals = torch.stack([signed_power(ce, 2 - e1) * signed_power(co, 2 - e2) / a,
                           signed_power(se, 2 - e1) / b,
                           signed_power(ce, 2 - e1) * signed_power(so, 2 - e2) / c], dim=-1)
    # At the poles with e1 > 2 the formula gives 0: fall back to the polar axis.
    degenerate = normals.norm(dim=-1, keepdim=True) < 1e-12
    polar = torch.zeros_like(normals)
    polar[:, 1] = torch.where(se >= 0, 1.0, -1.0).to(dtype)
    normals = torch.where(degenerate, polar, normals)
    return _cloud(points, normals, device if device is not None else points.device)
