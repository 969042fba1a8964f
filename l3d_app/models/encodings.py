"""Input encodings for neural fields: harmonic (positional) and multi-resolution grids.

* :class:`HarmonicEncoding` -- NeRF's positional encoding ``[x, sin(2^k x), cos(2^k x)]``.
* :class:`GridEncoding` -- a multi-resolution grid of learnable feature vectors (Instant-NGP
  style, pure PyTorch): each level is a dense vertex grid while it fits in the table size,
  a spatial hash table otherwise; features are trilinearly interpolated from the 8 cell
  corners and the levels concatenated. Fully vectorised over points, levels and corners.
"""

from __future__ import annotations

import math
from typing import Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.models.table_gather import gather_rows

#: Instant-NGP's spatial hash primes (the first is 1 so that x alone is coherent).
HASH_PRIMES = (1, 2654435761, 805459861)


class HarmonicEncoding(torch.nn.Module):
    """``gamma(x) = [x, sin(f_0 x), ..., sin(f_{n-1} x), cos(f_0 x), ..., cos(f_{n-1} x)]``.

    Frequencies ``f_k = omega0 * 2^k`` (k = 0 .. n-1); the sin (and cos) block is ordered
    dimension-major: ``sin(f_k x_d)`` sits at column ``d * n + k``. Input (..., D) ->
    output (..., D * (2n + include_input)). ``n_frequencies = 0`` gives x itself.
    """

    def __init__(self, in_dim: int = 3, n_frequencies: int = 6, omega0: float = 1.0,
                 include_input: bool = True):
        super().__init__()
        if n_frequencies < 0:
            raise UserError(f"n_frequencies must be >= 0, got {n_frequencies}")
        self.in_dim, self.n_frequencies, self.include_input = int(in_dim), int(n_frequencies), bool(include_input)
        self.register_buffer("frequencies", omega0 * 2.0 ** torch.arange(n_frequencies, dtype=torch.float32),
                             persistent=False)

    @property
    def out_dim(self) -> int:
        return self.in_dim * (2 * self.n_frequencies + int(self.include_input))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (..., D) -> (..., out_dim)."""
        scaled = (x[..., None] * self.frequencies.to(x.dtype)).flatten(-2)   # (..., D * n)
        parts = [x] if self.include_input else []
        return torch.cat(parts + [scaled.sin(), scaled.cos()], dim=-1)


def level_resolutions(n_levels: int, base_resolution: int, max_resolution: int) -> list:
    """Vertices per axis of each level, geometric from ``base`` to ``max`` (both >= 2)."""
    if n_levels < 1 or base_resolution < 2 or max_resolution < base_resolution:
        raise UserError(f"grid encoding needs n_levels >= 1 and 2 <= base_resolution <= max_resolution, "
                        f"got {n_levels}, {base_resolution}, {max_resolution}")
    if n_levels == 1:
        return [int(base_resolution)]
    growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (n_levels - 1))
    return [int(math.floor(base_resolution * growth ** level + 1e-6)) for level in range(n_levels)]


class GridEncoding(torch.nn.Module):
    """Multi-resolution dense/hash grid encoding over an axis-aligned box.

    Level ``l`` has ``R_l`` vertices per axis spanning the box (spacing
    ``(hi - lo) / (R_l - 1)``); it is stored densely (``R_l^3`` rows, index
    ``i + j R + k R^2``) when ``R_l^3 <= 2^log2_hashmap_size`` and hashed otherwise
    (``(i * 1 xor j * 2654435761 xor k * 805459861) mod 2^log2_hashmap_size``). All levels
    share one parameter table ``table`` (rows, n_features). Points outside the box are
    clamped to it.

    Args:
        n_levels: L; base_resolution / max_resolution: R_0 and R_{L-1} (vertices per axis).
        n_features: F features per level (output dim L * F).
        log2_hashmap_size: rows per hashed level = 2^T.
        bounds: ((x0, y0, z0), (x1, y1, z1)) world box.
        init_scale: table initialised uniformly in [-init_scale, init_scale].
    """

    def __init__(self, n_levels: int = 8, n_features: int = 2, base_resolution: int = 16,
                 max_resolution: int = 128, log2_hashmap_size: int = 17,
                 bounds: Tuple[Sequence[float], Sequence[float]] = ((-1.0,) * 3, (1.0,) * 3),
                 init_scale: float = 1e-4):
        super().__init__()
        res = level_resolutions(int(n_levels), int(base_resolution), int(max_resolution))
        cap = 2 ** int(log2_hashmap_size)
        sizes = [r ** 3 if r ** 3 <= cap else cap for r in res]
        offsets = [0]
        for s in sizes[:-1]:
            offsets.append(offsets[-1] + s)
        self.n_levels, self.n_features = len(res), int(n_features)
        self.register_buffer("resolution", torch.tensor(res, dtype=torch.int64), persistent=False)
        self.register_buffer("sizes", torch.tensor(sizes, dtype=torch.int64), persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.int64), persistent=False)
        self.register_buffer("hashed", torch.tensor([r ** 3 > cap for r in res]), persistent=False)
        lo = torch.as_tensor(bounds[0], dtype=torch.float32).reshape(3)
        hi = torch.as_tensor(bounds[1], dtype=torch.float32).reshape(3)
        if not bool((hi > lo).all()):
            raise UserError(f"grid encoding bounds need lo < hi per axis, got {bounds}")
        self.register_buffer("lo", lo, persistent=False)
        self.register_buffer("hi", hi, persistent=False)
        self.table = torch.nn.Parameter(
            (torch.rand(sum(sizes), self.n_features) * 2 - 1) * float(init_scale))

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features

    def corner_indices_and_weights(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Table rows (8, N, L) long and trilinear weights (8, N, L) for points x (N, 3).

        Corner c = (cx, cy, cz) in {0,1}^3 is row ``4 cx + 2 cy + cz``. Per axis the two
        candidate terms are computed once on contiguous (N, L) tensors and the 8 corners are
        their sums (dense: ``i + j R + k R^2``) or XORs (hash; sizes are powers of two, so the
        modulo is a bit mask; 64-bit products keep the low bits exact).
        """
        u = ((x - self.lo.to(x.dtype)) / (self.hi - self.lo).to(x.dtype)).clamp(0.0, 1.0)   # (N, 3)
        res = self.resolution                                                               # (L,)
        pos = u.t()[:, :, None] * (res - 1).to(x.dtype)[None, None, :]                      # (3, N, L)
        i0 = torch.minimum(pos.floor().long(), (res - 2)[None, None, :])                   # (3, N, L)
        frac = pos - i0.to(x.dtype)
        hashed = self.hashed[None, :]
        r = res[None, :]
        stride = (torch.where(hashed, 1, 1), torch.where(hashed, HASH_PRIMES[1], r),
                  torch.where(hashed, HASH_PRIMES[2], r * r))
        terms = [(i0[a] * stride[a], (i0[a] + 1) * stride[a]) for a in range(3)]           # (N, L) each
        weights = [(1 - frac[a], frac[a]) for a in range(3)]
        mask = self.sizes[None, :] - 1
        rows, wts = [], []
        for cx in (0, 1):
            for cy in (0, 1):
                for cz in (0, 1):
                    tx, ty, tz = terms[0][cx], terms[1][cy], terms[2][cz]
                    dense = tx + ty + tz
                    hash_ = (tx ^ ty ^ tz) & mask
                    rows.append(torch.where(hashed, hash_, dense))
                    wts.append(weights[0][cx] * weights[1][cy] * weights[2][cz])
        idx = torch.stack(rows, dim=0) + self.offsets[None, None, :]
        return idx, torch.stack(wts, dim=0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (N, 3) world points -> (N, L * F) interpolated features (level-major)."""
        idx, w = self.corner_indices_and_weights(x)
        # gather_rows: index_select forward (several times faster on CPU than F.embedding), bincount backward
        feats = gather_rows(self.table, idx.reshape(-1)).view(*idx.shape, self.n_features)     # (8, N, L, F)
        out = (w.to(feats.dtype)[..., None] * feats).sum(dim=0)                                  # (N, L, F)
        return out.reshape(x.shape[0], self.out_dim)
