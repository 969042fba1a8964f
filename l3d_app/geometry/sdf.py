"""Analytic signed distance functions (SDFs): small callables on points.

Every SDF here is an object with

- ``__call__(points)``: points (..., 3) float tensor (world units) -> (...) signed distances,
  negative inside, positive outside, zero on the surface; same dtype and device as the points;
- ``bounds()``: ``(lo, hi)``, two 3-tuples of floats, an axis-aligned box that contains the
  surface (tight for the primitives);
- ``exact``: True when the value is the true Euclidean distance to the surface everywhere
  (then ``|grad| = 1`` almost everywhere, the eikonal property).

Parameters are stored as Python floats, so one SDF works on any device and in any float dtype
(float64 included). Norms are "safe" (``sqrt(max(|x|^2, tiny))``) so that autograd gives finite
gradients at the kinks: a sphere's centre, a box's corners/edges/medial planes, a torus's core
circle and axis. There the gradient is a valid subgradient or zero, never NaN.

Conventions: +Y is up; the torus's axis of revolution and the superquadric's polar axis are Y.
These are reused by sphere tracing and SDF-based volume rendering (VolSDF).
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence, Tuple

import torch

from l3d_app.errors import UserError

Bounds = Tuple[Tuple[float, float, float], Tuple[float, float, float]]


def safe_norm(x: torch.Tensor, dim: int = -1, keepdim: bool = False) -> torch.Tensor:
    """Euclidean norm over ``dim`` with a finite gradient at 0 (where it returns ~sqrt(tiny)).

    ``sqrt(clamp_min(sum x^2, tiny))``: below ``tiny`` the clamp passes no gradient, so the
    backward pass never divides by zero. The bias is sqrt(tiny) (~1e-19 in float32).
    """
    sq = (x * x).sum(dim=dim, keepdim=keepdim)
    return sq.clamp_min(torch.finfo(x.dtype).tiny).sqrt()


def _vec3(value, name: str) -> Tuple[float, float, float]:
    v = tuple(float(x) for x in (value if isinstance(value, Iterable) else (value,) * 3))
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise UserError(f"{name} must be 3 finite numbers, got {value!r}")
    return v


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not value > 0 or not math.isfinite(value):
        raise UserError(f"{name} must be a positive number, got {value}")
    return value


def _check_points(points: torch.Tensor) -> None:
    if points.shape[-1:] != (3,):
        raise UserError(f"SDF points must be (..., 3), got {tuple(points.shape)}")


class SDF:
    """Base class: ``sdf(points (..., 3)) -> (...)``, ``sdf.bounds()``, ``sdf.exact``."""

    exact: bool = True

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        _check_points(points)
        return self.distance(points)

    def distance(self, points: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def bounds(self) -> Bounds:  # pragma: no cover - abstract
        raise NotImplementedError

    def translated(self, offset: Sequence[float]) -> "Translate":
        """This SDF moved by ``offset`` (3 world units)."""
        return Translate(self, offset)

    def __or__(self, other: "SDF") -> "Union":
        return Union([self, other])


class Sphere(SDF):
    """Sphere of ``radius`` around ``center``: ``|p - c| - r`` (exact)."""

    def __init__(self, radius: float = 1.0, center: Sequence[float] = (0.0, 0.0, 0.0)):
        self.radius = _positive("radius", radius)
        self.center = _vec3(center, "center")

    def distance(self, points: torch.Tensor) -> torch.Tensor:
        c = points.new_tensor(self.center)
        return safe_norm(points - c) - self.radius

    def bounds(self) -> Bounds:
        return (tuple(c - self.radius for c in self.center), tuple(c + self.radius for c in self.center))

    def __repr__(self) -> str:
        return f"Sphere(radius={self.radius}, center={self.center})"


def box_sdf(points: torch.Tensor, center: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """Exact signed distance (...) from points (..., 3) to the axis-aligned box of full side
    lengths ``size`` (3,) around ``center`` (3,); differentiable in all three (the box task
    learns ``center`` and ``size``). Formula: see :class:`Box`."""
    q = (points - center).abs() - size / 2
    return safe_norm(q.clamp_min(0.0)) + q.max(dim=-1).values.clamp_max(0.0)


class Box(SDF):
    """Axis-aligned box with full side lengths ``size`` around ``center`` (exact).

    With half sizes ``b`` and ``q = |p - c| - b`` (per axis):
    ``d = |max(q, 0)| + min(max(q_x, q_y, q_z), 0)`` — the distance to the nearest face, edge or
    corner outside, minus the distance to the nearest face inside.
    """

    def __init__(self, size: Sequence[float] = (1.0, 1.0, 1.0), center: Sequence[float] = (0.0, 0.0, 0.0)):
        self.size = tuple(_positive("box size", s) for s in _vec3(size, "size"))
        self.center = _vec3(center, "center")

    def distance(self, points: torch.Tensor) -> torch.Tensor:
        return box_sdf(points, points.new_tensor(self.center), points.new_tensor(self.size))

    def bounds(self) -> Bounds:
        return (tuple(c - s / 2 for c, s in zip(self.center, self.size)),
                tuple(c + s / 2 for c, s in zip(self.center, self.size)))

    def __repr__(self) -> str:
        return f"Box(size={self.size}, center={self.center})"


class Torus(SDF):
    """Torus around the Y axis through ``center`` (exact).

    ``major_radius`` R: centre to the tube's core circle (in the XZ plane); ``minor_radius`` r:
    the tube's radius (r < R for a ring torus). ``d = |(|p_xz| - R, p_y)| - r``.
    """

    def __init__(self, major_radius: float = 0.7, minor_radius: float = 0.3,
                 center: Sequence[float] = (0.0, 0.0, 0.0)):
        self.major_radius = _positive("major_radius", major_radius)
        self.minor_radius = _positive("minor_radius", minor_radius)
        self.center = _vec3(center, "center")

    def distance(self, points: torch.Tensor) -> torch.Tensor:
        p = points - points.new_tensor(self.center)
        ring = safe_norm(p[..., 0::2]) - self.major_radius  # distance to the Y axis, minus R
        return safe_norm(torch.stack([ring, p[..., 1]], dim=-1)) - self.minor_radius

    def bounds(self) -> Bounds:
        R, r = self.major_radius, self.minor_radius
        ext = (R + r, r, R + r)
        return (tuple(c - e for c, e in zip(self.center, ext)), tuple(c + e for c, e in zip(self.center, ext)))

    def __repr__(self) -> str:
        return f"Torus(major_radius={self.major_radius}, minor_radius={self.minor_radius}, center={self.center})"


class Superquadric(SDF):
    """Superellipsoid with semi-axes ``radii`` (a, b, c along X, Y, Z), polar axis Y (approximate).

    Inside-outside function (Barr 1981, with Y as the polar axis)::

        F(p) = (|x/a|^(2/e2) + |z/c|^(2/e2))^(e2/e1) + |y/b|^(2/e1)

    ``F < 1`` inside, ``F = 1`` on the surface, ``F > 1`` outside. ``e1`` shapes the polar
    (latitude) profile, ``e2`` the equatorial cross-section; ``e1 = e2 = 1`` is an ellipsoid,
    exponents -> 0 give a box, 2 an octahedron. ``G = F^(e1/2)`` is positively homogeneous of
    degree 1 (``G(s p) = s G(p)``), so the surface point on the ray from the centre through p is
    ``p / G(p)``. The value returned is that **radial** distance::

        d(p) = |p| - rho(u),   u = p / |p|,   rho(u) = 1 / G(u)  (the surface's radius along u)

    It has the right sign and zero set, and it is exact for spheres (a = b = c, e1 = e2 = 1).
    Otherwise it is an approximation that can OVER-estimate the Euclidean distance (the radial
    path is not the shortest), so a sphere tracer should take steps ``< 1 x`` this value, and
    ``|grad d|`` is not 1 in general (``exact = False``). At the centre ``d = -rho`` along +X.

    Exponents must be in (0, 4] and radii > 0. Powers are taken of ``max(|.|, tiny)`` so the
    gradient stays finite on the coordinate planes even for exponents 2/e < 1.
    """

    exact = False

    def __init__(self, radii: Sequence[float] = (0.8, 0.8, 0.8), exponents: Sequence[float] = (0.5, 0.5),
                 center: Sequence[float] = (0.0, 0.0, 0.0)):
        self.radii = tuple(_positive("superquadric radius", r) for r in _vec3(radii, "radii"))
        exps = tuple(float(e) for e in exponents)
        if len(exps) != 2 or not all(0.0 < e <= 4.0 for e in exps):
            raise UserError(f"superquadric exponents must be two numbers in (0, 4], got {list(exponents)}")
        self.exponents = exps
        self.center = _vec3(center, "center")

    def inside_outside(self, points: torch.Tensor) -> torch.Tensor:
        """F(p) (...) for points (..., 3): < 1 inside, 1 on the surface, > 1 outside."""
        p = points - points.new_tensor(self.center)
        return self._F(p)

    def _F(self, p: torch.Tensor) -> torch.Tensor:
        e1, e2 = self.exponents
        tiny = torch.finfo(p.dtype).tiny
        s = (p / p.new_tensor(self.radii)).abs().clamp_min(tiny)
        xz = s[..., 0].pow(2.0 / e2) + s[..., 2].pow(2.0 / e2)
        return xz.pow(e2 / e1) + s[..., 1].pow(2.0 / e1)

    def distance(self, points: torch.Tensor) -> torch.Tensor:
        p = points - points.new_tensor(self.center)
        norm = safe_norm(p, keepdim=True)
        at_centre = norm <= torch.finfo(p.dtype).tiny ** 0.25
        x_axis = torch.zeros_like(p)
        x_axis[..., 0] = 1.0
        u = torch.where(at_centre, x_axis, p / norm)            # unit direction (..., 3)
        g = self._F(u).pow(self.exponents[0] / 2)                # G(u) > 0, bounded for unit u
        return norm[..., 0] - 1.0 / g

    def bounds(self) -> Bounds:
        return (tuple(c - r for c, r in zip(self.center, self.radii)),
                tuple(c + r for c, r in zip(self.center, self.radii)))

    def __repr__(self) -> str:
        return f"Superquadric(radii={self.radii}, exponents={self.exponents}, center={self.center})"


class Translate(SDF):
    """``sdf`` moved by ``offset``: ``d(p) = sdf(p - offset)`` (exact iff ``sdf`` is)."""

    def __init__(self, sdf: SDF, offset: Sequence[float]):
        self.sdf = sdf
        self.offset = _vec3(offset, "offset")
        self.exact = sdf.exact

    def distance(self, points: torch.Tensor) -> torch.Tensor:
        return self.sdf(points - points.new_tensor(self.offset))

    def bounds(self) -> Bounds:
        lo, hi = self.sdf.bounds()
        return (tuple(a + o for a, o in zip(lo, self.offset)), tuple(a + o for a, o in zip(hi, self.offset)))

    def __repr__(self) -> str:
        return f"Translate({self.sdf!r}, offset={self.offset})"


class Union(SDF):
    """Union of shapes: ``d = min_i d_i``.

    Exact outside the union when every part is exact; inside (and where parts overlap) it is a
    lower bound of the true distance to the union's surface, so ``exact = False``. The gradient
    is that of the nearest part (finite; at ties one of them).
    """

    exact = False

    def __init__(self, parts: Sequence[SDF]):
        self.parts = list(parts)
        if not self.parts:
            raise UserError("a union needs at least one shape")

    def distance(self, points: torch.Tensor) -> torch.Tensor:
        return torch.stack([part(points) for part in self.parts], dim=-1).min(dim=-1).values

    def bounds(self) -> Bounds:
        boxes = [part.bounds() for part in self.parts]
        lo = tuple(min(b[0][i] for b in boxes) for i in range(3))
        hi = tuple(max(b[1][i] for b in boxes) for i in range(3))
        return lo, hi

    def __repr__(self) -> str:
        return f"Union({self.parts!r})"
