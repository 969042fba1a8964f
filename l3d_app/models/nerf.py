"""Radiance fields: the NeRF MLP (harmonic encoding) and a fast grid field (grid encoding + small MLP).

Both are callables ``field(points (N, 3), dirs (N, 3)) -> (sigma (N,), rgb (N, 3))`` with
``sigma >= 0`` a density in 1 / world units and ``rgb`` in [0, 1] (the interface of
:class:`~l3d_app.render.volume.renderer.VolumeRenderer`), plus ``density(points) -> (N,)`` for the
occupancy grid and mesh extraction. ``dirs`` are unit ray directions (world frame).
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch
import torch.nn.functional as F

from l3d_app.errors import UserError
from l3d_app.models.encodings import GridEncoding, HarmonicEncoding
from l3d_app.registry import MODELS

_ACTIVATIONS = ("relu", "softplus", "exp")


def density_activation(raw: torch.Tensor, kind: str) -> torch.Tensor:
    """Raw network output -> density >= 0. ``exp`` is clamped at e^15 (finite gradients)."""
    if kind == "relu":
        return F.relu(raw)
    if kind == "softplus":
        return F.softplus(raw)
    return torch.exp(raw.clamp(max=15.0))


def _check_activation(kind: str) -> None:
    if kind not in _ACTIVATIONS:
        raise UserError(f"density_activation must be one of {', '.join(_ACTIVATIONS)}, got {kind!r}")


@MODELS.register("nerf_mlp")
class NeRFMLP(torch.nn.Module):
    """The NeRF MLP (as in the course): harmonic(xyz) -> ``n_layers`` x ``hidden`` ReLU layers,
    with the encoded input concatenated again to the input of each layer in ``skips`` ->
    density head (1) and a colour head (feature -> [+ harmonic(dir)] -> hidden/2 -> 3, sigmoid).

    Args:
        n_layers, hidden: trunk depth and width (course: 6 x 128).
        skips: trunk layer indices (0-based) whose input gets the encoded xyz appended (course: [3]).
        n_freq_xyz, n_freq_dir: harmonic frequencies of positions / directions (course: 6 / 2).
        omega0: frequency base of the position encoding, ``f_k = omega0 2^k`` (1: the course;
            pi: the NeRF paper's ``2^k pi``).
        use_viewdirs: colour depends on the view direction.
        density_activation: relu (course) | softplus | exp.
        scene_box: accepted for a uniform model interface (positions are used raw).
    """

    def __init__(self, n_layers: int = 6, hidden: int = 128, skips: Sequence[int] = (3,),
                 n_freq_xyz: int = 6, n_freq_dir: int = 2, use_viewdirs: bool = True,
                 density_activation: str = "relu", scene_box=None, omega0: float = 1.0):
        super().__init__()
        _check_activation(density_activation)
        if n_layers < 1 or hidden < 1:
            raise UserError(f"nerf_mlp needs n_layers >= 1 and hidden >= 1, got {n_layers}, {hidden}")
        if not float(omega0) > 0:
            raise ValueError(f"omega0 must be > 0, got {omega0}")
        self.enc_xyz = HarmonicEncoding(3, n_freq_xyz, omega0=float(omega0))
        self.enc_dir = HarmonicEncoding(3, n_freq_dir) if use_viewdirs else None
        self.skips = set(int(s) for s in skips)
        layers, d_in = [], self.enc_xyz.out_dim
        for i in range(n_layers):
            extra = self.enc_xyz.out_dim if (i in self.skips and i > 0) else 0
            layers.append(torch.nn.Linear((d_in if i == 0 else hidden) + extra, hidden))
        self.trunk = torch.nn.ModuleList(layers)
        self.sigma_head = torch.nn.Linear(hidden, 1)
        self.feature = torch.nn.Linear(hidden, hidden)
        d_dir = self.enc_dir.out_dim if self.enc_dir is not None else 0
        self.color_head = torch.nn.Sequential(torch.nn.Linear(hidden + d_dir, hidden // 2), torch.nn.ReLU(),
                                              torch.nn.Linear(hidden // 2, 3))
        self.activation = density_activation

    def _trunk(self, points: torch.Tensor) -> torch.Tensor:
        e = self.enc_xyz(points)
        h = e
        for i, layer in enumerate(self.trunk):
            if i in self.skips and i > 0:
                h = torch.cat([h, e], dim=-1)
            h = F.relu(layer(h))
        return h

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """points (N, 3) -> sigma (N,) >= 0."""
        return density_activation(self.sigma_head(self._trunk(points))[..., 0], self.activation)

    def forward(self, points: torch.Tensor, dirs: Optional[torch.Tensor] = None
                ) -> Tuple[torch.Tensor, torch.Tensor]:
        """points, dirs (N, 3) -> sigma (N,), rgb (N, 3)."""
        h = self._trunk(points)
        sigma = density_activation(self.sigma_head(h)[..., 0], self.activation)
        feat = self.feature(h)
        if self.enc_dir is not None:
            if dirs is None:
                raise UserError("this nerf_mlp uses view directions: pass dirs")
            feat = torch.cat([feat, self.enc_dir(dirs)], dim=-1)
        return sigma, torch.sigmoid(self.color_head(feat))


@MODELS.register("grid_field")
class GridField(torch.nn.Module):
    """Fast radiance field: :class:`GridEncoding` over the scene box -> small MLPs.

    ``geo = MLP_geo(grid(x))`` (``geo_layers`` hidden layers of width ``hidden``) gives the raw
    density (first output, through ``density_activation``) and ``geo_features`` features;
    ``rgb = sigmoid(MLP_rgb([geo_features, harmonic(dir)]))`` (the direction part only with
    ``use_viewdirs``).

    Args:
        scene_box: ((x0, y0, z0), (x1, y1, z1)) world box covered by the grid (required).
        n_levels, n_features, base_resolution, max_resolution, log2_hashmap_size: see
            :class:`GridEncoding`.
        hidden, geo_layers, geo_features, color_layers: MLP sizes.
        use_viewdirs, n_freq_dir: view dependence (off by default: diffuse scenes).
        density_activation: exp (default, clamped) | softplus | relu.
        density_bias: added to the raw density before the activation (exp(-1): a nearly
            transparent start).
    """

    def __init__(self, scene_box=None, n_levels: int = 8, n_features: int = 2, base_resolution: int = 16,
                 max_resolution: int = 128, log2_hashmap_size: int = 17, hidden: int = 64,
                 geo_layers: int = 1, geo_features: int = 15, color_layers: int = 1,
                 use_viewdirs: bool = False, n_freq_dir: int = 2, density_activation: str = "exp",
                 density_bias: float = -1.0):
        super().__init__()
        _check_activation(density_activation)
        if scene_box is None:
            raise UserError("grid_field needs the scene box (the data source provides it)")
        self.encoding = GridEncoding(n_levels, n_features, base_resolution, max_resolution,
                                     log2_hashmap_size, bounds=scene_box)
        self.geo = _mlp(self.encoding.out_dim, hidden, 1 + geo_features, geo_layers)
        self.enc_dir = HarmonicEncoding(3, n_freq_dir) if use_viewdirs else None
        d_dir = self.enc_dir.out_dim if self.enc_dir is not None else 0
        self.rgb = _mlp(geo_features + d_dir, hidden, 3, color_layers)
        self.activation, self.density_bias = density_activation, float(density_bias)

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """points (N, 3) -> sigma (N,) >= 0."""
        return density_activation(self.geo(self.encoding(points))[..., 0] + self.density_bias, self.activation)

    def forward(self, points: torch.Tensor, dirs: Optional[torch.Tensor] = None
                ) -> Tuple[torch.Tensor, torch.Tensor]:
        """points, dirs (N, 3) -> sigma (N,), rgb (N, 3)."""
        g = self.geo(self.encoding(points))
        sigma = density_activation(g[..., 0] + self.density_bias, self.activation)
        feat = g[..., 1:]
        if self.enc_dir is not None:
            feat = torch.cat([feat, self.enc_dir(dirs)], dim=-1)
        return sigma, torch.sigmoid(self.rgb(feat))


def _mlp(d_in: int, hidden: int, d_out: int, n_hidden: int) -> torch.nn.Sequential:
    """``n_hidden`` ReLU layers of width ``hidden`` then a linear output layer."""
    layers, d = [], d_in
    for _ in range(int(n_hidden)):
        layers += [torch.nn.Linear(d, hidden), torch.nn.ReLU()]
        d = hidden
    layers.append(torch.nn.Linear(d, d_out))
    return torch.nn.Sequential(*layers)
