"""Surfaces from functions as data sources: ``data=<shape>_parametric`` / ``data=<shape>_implicit``.

- ``parametric`` (:func:`parametric_surface`): a PointCloud sampled from a parametric form
  (torus, superquadric), parameters i.i.d. uniform, seeded.
- ``implicit`` (:func:`implicit_surface`): a Mesh extracted by marching cubes from an analytic
  SDF (sphere, box, torus, superquadric, or a union of a sphere, a box and a torus).

Both colour the surface by its normal (``0.5 + 0.5 n``). Shapes are centred at the origin,
+Y up, inside the unit sphere with the default parameters.
"""

from __future__ import annotations

from typing import Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry import sdf as S
from l3d_app.geometry.marching_cubes import sdf_to_mesh
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.parametric import superquadric_points, torus_points
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.registry import DATASETS

PARAMETRIC_SHAPES = ("torus", "superquadric")
IMPLICIT_SHAPES = ("sphere", "box", "torus", "superquadric", "union")


def union_scene(major_radius: float = 0.35, minor_radius: float = 0.12) -> S.SDF:
    """The ``union`` shape: a sphere (left), a box (right) and a torus (top), overlapping a little."""
    return S.Union([
        S.Sphere(0.4, center=(-0.42, -0.15, 0.0)),
        S.Box((0.6, 0.6, 0.6), center=(0.4, -0.2, 0.0)),
        S.Torus(major_radius, minor_radius, center=(0.0, 0.35, 0.0)),
    ])


def make_sdf(shape: str, major_radius: float = 0.7, minor_radius: float = 0.3,
             radii: Sequence[float] = (0.8, 0.8, 0.8), exponents: Sequence[float] = (0.5, 0.5),
             radius: float = 0.8, size: Sequence[float] = (1.0, 1.0, 1.0)) -> S.SDF:
    """The analytic SDF of a named shape (see ``IMPLICIT_SHAPES``), centred at the origin."""
    if shape == "sphere":
        return S.Sphere(radius)
    if shape == "box":
        return S.Box(size)
    if shape == "torus":
        return S.Torus(major_radius, minor_radius)
    if shape == "superquadric":
        return S.Superquadric(radii, exponents)
    if shape == "union":
        return union_scene()
    raise UserError(f"unknown implicit shape '{shape}'. Known: {', '.join(IMPLICIT_SHAPES)}")


@DATASETS.register("parametric")
def parametric_surface(shape: str = "torus", num_samples: int = 10000, major_radius: float = 0.7,
                       minor_radius: float = 0.3, radii: Sequence[float] = (0.8, 0.8, 0.8),
                       exponents: Sequence[float] = (0.5, 0.5), area_uniform: bool = False,
                       device=None, seed: int = 0) -> PointCloud:
    """``num_samples`` points (N, 3) on a parametric ``shape`` with normals and normal colours.

    torus: around Y, ``major_radius``/``minor_radius``; ``area_uniform`` switches from uniform
    parameters to exact area-uniform samples. superquadric: semi-axes ``radii`` (X, Y, Z) and
    ``exponents`` (e1 polar, e2 equatorial). Sampled on the CPU from ``seed``, then moved to
    ``device``.
    """
    gen = torch.Generator().manual_seed(int(seed))
    if shape == "torus":
        cloud = torus_points(num_samples, major_radius, minor_radius, gen, area_uniform=area_uniform)
    elif shape == "superquadric":
        if area_uniform:
            raise UserError("area_uniform is only implemented for the torus")
        cloud = superquadric_points(num_samples, radii, exponents, gen)
    else:
        raise UserError(f"unknown parametric shape '{shape}'. Known: {', '.join(PARAMETRIC_SHAPES)}")
    return cloud.to(device=device)


@DATASETS.register("implicit")
def implicit_surface(shape: str = "torus", resolution: int = 64, major_radius: float = 0.7,
                     minor_radius: float = 0.3, radii: Sequence[float] = (0.8, 0.8, 0.8),
                     exponents: Sequence[float] = (0.5, 0.5), radius: float = 0.8,
                     size: Sequence[float] = (1.0, 1.0, 1.0), level: float = 0.0,
                     device=None) -> Mesh:
    """Marching-cubes Mesh of the zero level set (or ``level``) of the analytic SDF of ``shape``
    on a ``resolution``^3 grid over its padded bounds; vertex colours by normal.

    Shapes: sphere (``radius``), box (side lengths ``size``), torus (``major_radius``,
    ``minor_radius``), superquadric (``radii``, ``exponents``), union (sphere + box + torus).
    """
    sdf = make_sdf(shape, major_radius, minor_radius, radii, exponents, radius, size)
    mesh = sdf_to_mesh(sdf, int(resolution), level=float(level))
    return mesh.to(device=device)
