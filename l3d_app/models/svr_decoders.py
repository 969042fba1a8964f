"""Single-view-reconstruction decoders: image feature -> voxels, points, mesh, occupancy field.

Every decoder maps the encoder's ``(B, latent_dim)`` feature to a shape in the canonical
object box (``geometry["bounds"]``, default ``[-1, 1]^3``: the data's box) and offers the
same two methods, so the tasks treat them alike; its ``kind`` names its training loss in
:mod:`l3d_app.losses.svr` (models import no loss, metric or data module):

* ``shapes(feature) -> list`` of B predicted shapes for pictures (:class:`Mesh`,
  :class:`PointCloud` or None when the prediction is empty);
* ``points(feature, num_points, generator) -> list`` of B ``(P_i, 3)`` point sets for
  chamfer / F1 (surface samples of meshes, the predicted points themselves).

Decoders (registered in ``MODELS``, configs in ``conf/decoder/``):

* ``svr_vox``: transposed 3D convolutions from a 4^3 seed to ``voxel_size``^3 occupancy
  logits (Pix2Vox-F style); meshed by marching cubes.
* ``svr_point``: MLP to ``num_points x 3`` (tanh, inside the box).
* ``svr_mesh``: MLP to per-vertex offsets of an icosphere (last layer zero-initialised, so
  training starts from the sphere).
* ``svr_implicit``: occupancy network: harmonic encoding of query points concatenated with
  the feature (the first layer split into a per-point and a per-object product), MLP to a
  logit; meshed by marching cubes of the field at the cell centres of a
  ``mesh_resolution``^3 grid.
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple

import torch
from torch import nn

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.primitives import icosphere
from l3d_app.geometry.sampling import sample_surface, uniform_barycentrics
from l3d_app.geometry.voxels import occupancy_to_mesh, voxel_centers
from l3d_app.models.encodings import HarmonicEncoding
from l3d_app.registry import MODELS

Bounds = Tuple[Tuple[float, float, float], Tuple[float, float, float]]
BOUNDS: Bounds = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))  # default object box (old model files)


def bounds_of(geometry: Dict) -> Bounds:
    """The object box of the data (``geometry["bounds"]``), else :data:`BOUNDS`."""
    lo, hi = geometry.get("bounds", BOUNDS)
    return (tuple(float(x) for x in lo), tuple(float(x) for x in hi))


def mlp(sizes: Sequence[int], last_zero: bool = False) -> nn.Sequential:
    """Linear layers of ``sizes`` with ReLU between them (none after the last)."""
    layers: List[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(int(a), int(b)))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU(inplace=True))
    if last_zero:
        nn.init.zeros_(layers[-1].weight)
        nn.init.zeros_(layers[-1].bias)
    return nn.Sequential(*layers)


def mesh_points(meshes: List[Optional[Mesh]], num_points: int, generator) -> List[torch.Tensor]:
    """Surface samples of each mesh ((0, 3) for None)."""
    out = []
    for m in meshes:
        if m is None or m.num_faces == 0:
            out.append(torch.zeros(0, 3))
        else:
            m = m if generator is None else m.to(generator.device)  # draws where the generator is
            out.append(sample_surface(m, num_points, generator).points.detach())
    return out


def field_to_mesh(probabilities: torch.Tensor, level: float = 0.5, bounds: Bounds = BOUNDS) -> Optional[Mesh]:
    """Marching cubes at ``level`` of an (R, R, R) occupancy over ``bounds`` (None if empty)."""
    try:
        return occupancy_to_mesh(probabilities.detach().float().cpu(), bounds, level=float(level), colors="normal")
    except UserError:  # nothing occupied
        return None


# ----------------------------------------------------------------------- voxels
class VoxelDecoder(nn.Module):
    """Feature -> (B, R, R, R) occupancy logits by transposed 3D convolutions (k 4, stride 2)."""

    kind = "vox"

    def __init__(self, latent_dim: int, voxel_size: int = 32, width: int = 32, pos_weight: Optional[float] = None,
                 level: float = 0.5, bounds: Bounds = BOUNDS):
        super().__init__()
        self.bounds = bounds
        R = int(voxel_size)
        ups = int(round(math.log2(R / 4))) if R >= 4 else -1
        if ups < 0 or 4 * 2 ** ups != R:
            raise UserError(f"svr_vox needs voxel_size = 4 * 2^k (8, 16, 32, 64), got {voxel_size}")
        self.R, self.width, self.pos_weight, self.level = R, int(width), pos_weight, float(level)
        self.seed = nn.Sequential(nn.Linear(int(latent_dim), self.width * 64), nn.ReLU(inplace=True))
        layers: List[nn.Module] = []
        c = self.width
        for _ in range(ups):
            nxt = max(c // 2, 4)
            # no normalisation: GroupNorm over the whole map made every object's output alike
            layers += [nn.ConvTranspose3d(c, nxt, 4, 2, 1), nn.ReLU(inplace=True)]
            c = nxt
        layers.append(nn.Conv3d(c, 1, 1))
        self.up = nn.Sequential(*layers)

    def forward(self, feature: torch.Tensor) -> torch.Tensor:
        """(B, latent) -> (B, R, R, R) logits, indexed [x, y, z] like the voxel grids."""
        x = self.seed(feature).view(-1, self.width, 4, 4, 4)
        return self.up(x)[:, 0]

    def shapes(self, feature) -> List[Optional[Mesh]]:
        return [field_to_mesh(p, self.level, self.bounds) for p in torch.sigmoid(self(feature))]

    def points(self, feature, num_points: int, generator=None) -> List[torch.Tensor]:
        return mesh_points(self.shapes(feature), num_points, generator)


# ----------------------------------------------------------------------- points
class PointDecoder(nn.Module):
    """Feature -> (B, N, 3) points by an MLP (tanh: inside the box); ``target_points``: the
    surface samples its chamfer loss compares with."""

    kind = "point"

    def __init__(self, latent_dim: int, num_points: int = 1024, hidden: Sequence[int] = (512, 512),
                 target_points: int = 1024):
        super().__init__()
        self.num_points, self.target_points = int(num_points), int(target_points)
        self.net = mlp([int(latent_dim), *hidden, 3 * self.num_points])

    def forward(self, feature: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(feature)).view(-1, self.num_points, 3)

    def shapes(self, feature) -> List[PointCloud]:
        return [PointCloud(p.detach()) for p in self(feature)]

    def points(self, feature, num_points: int = 0, generator=None) -> List[torch.Tensor]:
        return [p.detach() for p in self(feature)]


# ------------------------------------------------------------------------- mesh
def sample_meshes(verts: torch.Tensor, faces: torch.Tensor, n: int, generator=None) -> torch.Tensor:
    """(B, n, 3) area-uniform samples on B meshes sharing ``faces`` (F, 3), with gradients
    to ``verts`` (B, V, 3) (batched twin-free version of ``sample_surface``'s scheme:
    faces by area, then uniform barycentrics). ``generator``: a CPU generator (the draws
    are made on the CPU and moved to ``verts``' device)."""
    B = verts.shape[0]
    fv = verts[:, faces]                                            # (B, F, 3, 3)
    area = torch.cross(fv[:, :, 1] - fv[:, :, 0], fv[:, :, 2] - fv[:, :, 0], dim=-1).norm(dim=-1)
    weights = area.detach().double().cpu() + 1e-12                  # never all-zero
    face = torch.multinomial(weights, n, replacement=True, generator=generator).to(verts.device)  # (B, n)
    bary = uniform_barycentrics(B * n, generator, dtype=verts.dtype).to(verts.device).view(B, n, 3)
    tri = torch.gather(fv, 1, face[..., None, None].expand(-1, -1, 3, 3))       # (B, n, 3, 3)
    return (bary[..., None] * tri).sum(dim=2)


class MeshDecoder(nn.Module):
    """Feature -> per-vertex offsets of an icosphere (level ``ico_level``, ``init_radius``);
    ``w_chamfer``, ``w_smooth``, ``num_samples``: its loss's weights and sample count."""

    kind = "mesh"

    def __init__(self, latent_dim: int, ico_level: int = 3, init_radius: float = 0.5,
                 hidden: Sequence[int] = (512, 512), w_chamfer: float = 1.0, w_smooth: float = 0.1,
                 num_samples: int = 1024):
        super().__init__()
        sphere = icosphere(int(ico_level), float(init_radius))
        self.register_buffer("template", sphere.verts.float())
        self.register_buffer("faces", sphere.faces.long())
        self.w_chamfer, self.w_smooth, self.num_samples = float(w_chamfer), float(w_smooth), int(num_samples)
        self.net = mlp([int(latent_dim), *hidden, 3 * sphere.num_verts], last_zero=True)

    def forward(self, feature: torch.Tensor) -> torch.Tensor:
        """(B, latent) -> (B, V, 3) vertex positions."""
        return self.template + self.net(feature).view(feature.shape[0], -1, 3)

    def sample(self, verts: torch.Tensor, n: int, generator=None) -> torch.Tensor:
        """(B, n, 3) area-uniform samples of the meshes with vertices ``verts`` (B, V, 3)."""
        return sample_meshes(verts, self.faces, int(n), generator)

    def shapes(self, feature) -> List[Mesh]:
        return [Mesh(verts=v.detach(), faces=self.faces) for v in self(feature)]

    def points(self, feature, num_points: int, generator=None) -> List[torch.Tensor]:
        return list(sample_meshes(self(feature), self.faces, int(num_points), generator).detach())


# --------------------------------------------------------------------- implicit
class ImplicitDecoder(nn.Module):
    """Occupancy network: logit(p | feature) for query points p (B, Q, 3); ``queries``: labelled
    points per object its loss reads."""

    kind = "implicit"

    def __init__(self, latent_dim: int, hidden: int = 128, layers: int = 3, n_frequencies: int = 4,
                 queries: int = 1024, mesh_resolution: int = 32, pos_weight: Optional[float] = None,
                 bounds: Bounds = BOUNDS):
        super().__init__()
        self.bounds = bounds
        self.encoding = HarmonicEncoding(3, int(n_frequencies))
        # first layer split in a per-point and a per-object part: W [enc(p), f] = W_p enc(p) + W_f f
        self.point_in = nn.Linear(self.encoding.out_dim, int(hidden))
        self.feature_in = nn.Linear(int(latent_dim), int(hidden), bias=False)
        self.net = mlp([int(hidden)] * int(layers) + [1])
        self.queries, self.mesh_resolution, self.pos_weight = int(queries), int(mesh_resolution), pos_weight

    def forward(self, feature: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """feature (B, latent), points (B, Q, 3) -> (B, Q) logits."""
        h = self.point_in(self.encoding(points)) + self.feature_in(feature)[:, None]
        return self.net(torch.relu(h))[..., 0]

    def grid(self, feature) -> torch.Tensor:
        """(B, R, R, R) occupancy probabilities at the cell centres of the grid over the box."""
        R = self.mesh_resolution
        centers = voxel_centers(R, self.bounds, device=feature.device).reshape(1, -1, 3)
        probs = [torch.sigmoid(self(f[None], centers)) for f in feature]  # one object at a time (memory)
        return torch.cat(probs).view(-1, R, R, R)

    def shapes(self, feature) -> List[Optional[Mesh]]:
        return [field_to_mesh(p, 0.5, self.bounds) for p in self.grid(feature)]

    def points(self, feature, num_points: int, generator=None) -> List[torch.Tensor]:
        return mesh_points(self.shapes(feature), num_points, generator)


@MODELS.register("svr_vox")
def svr_vox(latent_dim: int, geometry: Dict, width: int = 32, pos_weight: Optional[float] = None,
            level: float = 0.5) -> VoxelDecoder:
    """Voxel decoder at the data's ``voxel_size``; ``level``: the probability meshed by marching cubes."""
    return VoxelDecoder(latent_dim, int(geometry["voxel_size"]), width, pos_weight, level, bounds_of(geometry))


@MODELS.register("svr_point")
def svr_point(latent_dim: int, geometry: Dict, num_points: int = 1024, hidden: Sequence[int] = (512, 512),
              target_points: int = 1024) -> PointDecoder:
    return PointDecoder(latent_dim, num_points, hidden, target_points)


@MODELS.register("svr_mesh")
def svr_mesh(latent_dim: int, geometry: Dict, ico_level: int = 3, init_radius: float = 0.5,
             hidden: Sequence[int] = (512, 512), w_chamfer: float = 1.0, w_smooth: float = 0.1,
             num_samples: int = 1024) -> MeshDecoder:
    return MeshDecoder(latent_dim, ico_level, init_radius, hidden, w_chamfer, w_smooth, num_samples)


@MODELS.register("svr_implicit")
def svr_implicit(latent_dim: int, geometry: Dict, hidden: int = 128, layers: int = 3, n_frequencies: int = 4,
                 queries: int = 1024, mesh_resolution: int = 32, pos_weight: Optional[float] = None) -> ImplicitDecoder:
    return ImplicitDecoder(latent_dim, hidden, layers, n_frequencies, queries, mesh_resolution, pos_weight,
                           bounds_of(geometry))
