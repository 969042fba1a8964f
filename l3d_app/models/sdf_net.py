"""Neural signed distance fields: an SDF MLP (geometric init to a sphere) and a colour network.

:class:`SDFNetwork`: ``x (N, 3) -> [f (N,), features (N, F)]``, encoding ``gamma(x)``
(:class:`~l3d_app.models.encodings.HarmonicEncoding`, or a
:class:`~l3d_app.models.encodings.GridEncoding` over the scene box concatenated with ``x``),
then ``n_layers`` Softplus(beta=100) layers and a linear output WITHOUT activation (an SDF
takes any sign). Geometric initialisation (Atzmon & Lipman, SAL 2020, with NeuS's rule for
encoded inputs): hidden weights ``N(0, 2/width)``, the encoded (non-``x``) input columns and
all biases 0, the SDF row of the last layer ``N(sqrt(pi)/sqrt(width), 1e-4)`` with bias
``-radius``; the net then starts close to ``|x| - radius`` (a sphere), which
:func:`pretrain_sphere` makes precise.

:class:`ColorNetwork`: ``rgb = sigmoid(MLP([x, features(, dir)]))`` -- conditioned on the
position and the SDF network's features (optionally the view direction).
"""

from __future__ import annotations

import math
from typing import Callable, Iterable, Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.models.encodings import GridEncoding, HarmonicEncoding
from l3d_app.registry import MODELS


class SDFNetwork(torch.nn.Module):
    """SDF MLP (see the module docstring).

    Args:
        n_frequencies: harmonic frequencies of the encoding (0: raw x).
        hidden, n_layers: width and number of hidden layers.
        n_features: feature outputs besides the SDF (0: SDF only).
        radius: the sphere of the geometric initialisation (world units).
        encoding: ``harmonic`` or ``grid`` (multi-resolution grid over ``scene_box`` + x).
        scene_box: ((x0, y0, z0), (x1, y1, z1)), needed by ``grid``.
        grid: keyword arguments of :class:`GridEncoding` (n_levels, n_features, ...).
    """

    def __init__(self, n_frequencies: int = 6, hidden: int = 64, n_layers: int = 3, n_features: int = 16,
                 radius: float = 0.5, encoding: str = "harmonic", scene_box=None, grid: Optional[dict] = None,
                 softplus_beta: float = 100.0):
        super().__init__()
        if encoding == "harmonic":
            self.encoding = HarmonicEncoding(3, int(n_frequencies))
            d_in = self.encoding.out_dim
        elif encoding == "grid":
            if scene_box is None:
                raise UserError("the grid SDF encoding needs scene_box")
            self.encoding = GridEncoding(bounds=scene_box, **dict(grid or {}))
            d_in = 3 + self.encoding.out_dim
        else:
            raise UserError(f"unknown SDF encoding '{encoding}'. Known: harmonic, grid")
        if int(n_layers) < 1 or int(hidden) < 1:
            raise UserError(f"SDF network needs n_layers >= 1 and hidden >= 1, got {n_layers}, {hidden}")
        self.kind, self.n_features, self.radius = encoding, int(n_features), float(radius)
        dims = [d_in] + [int(hidden)] * int(n_layers)
        self.layers = torch.nn.ModuleList(torch.nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.out = torch.nn.Linear(dims[-1], 1 + self.n_features)
        self.act = torch.nn.Softplus(beta=float(softplus_beta))
        geometric_init(self.layers, self.out, self.radius)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        if self.kind == "grid":
            return torch.cat([x, self.encoding(x)], dim=-1)
        return self.encoding(x)

    def forward(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """x (N, 3) world units -> SDF (N,) world units, features (N, n_features)."""
        h = self.encode(x)
        for lin in self.layers:
            h = self.act(lin(h))
        out = self.out(h)
        return out[..., 0], out[..., 1:]

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """x (..., 3) -> SDF (...)."""
        return self(x.reshape(-1, 3))[0].reshape(x.shape[:-1])

    def gradient(self, x: torch.Tensor, create_graph: bool = True) -> Tuple[torch.Tensor, torch.Tensor]:
        """SDF (N,) and its spatial gradient (N, 3) at x (N, 3) (``create_graph`` for losses on it)."""
        with torch.enable_grad():
            x = x if x.requires_grad else x.detach().requires_grad_(True)
            f = self(x)[0]
            (g,) = torch.autograd.grad(f.sum(), x, create_graph=create_graph)
        return f, g


class ColorNetwork(torch.nn.Module):
    """``rgb (N, 3) in [0, 1] = sigmoid(MLP([x, features(, harmonic(dir))]))``."""

    def __init__(self, n_features: int = 16, hidden: int = 64, n_layers: int = 2, use_viewdirs: bool = False,
                 n_freq_dir: int = 2):
        super().__init__()
        self.enc_dir = HarmonicEncoding(3, int(n_freq_dir)) if use_viewdirs else None
        d = 3 + int(n_features) + (self.enc_dir.out_dim if self.enc_dir is not None else 0)
        layers = []
        for _ in range(int(n_layers)):
            layers += [torch.nn.Linear(d, int(hidden)), torch.nn.ReLU()]
            d = int(hidden)
        layers.append(torch.nn.Linear(d, 3))
        self.mlp = torch.nn.Sequential(*layers)

    def forward(self, x: torch.Tensor, features: torch.Tensor, dirs: Optional[torch.Tensor] = None) -> torch.Tensor:
        parts = [x, features]
        if self.enc_dir is not None:
            parts.append(self.enc_dir(dirs))
        return torch.sigmoid(self.mlp(torch.cat(parts, dim=-1)))



@torch.no_grad()
def geometric_init(layers: Sequence[torch.nn.Linear], out: torch.nn.Linear, radius: float) -> None:
    """Geometric initialisation (Atzmon & Lipman, SAL) of an SDF MLP to a sphere of ``radius``.

    ``layers``: the hidden Linear layers whose first takes ``[x (3), encoded features]``; only
    the xyz columns start non-zero, so the start is the sphere whatever the encoding gives.
    ``out``: the output Linear whose first row is the SDF (the others are features, ~0).
    Meant for Softplus hidden activations; at step 0, f(x) is close to ``|x| - radius``.
    """
    for i, lin in enumerate(layers):
        torch.nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(lin.out_features))
        torch.nn.init.zeros_(lin.bias)
        if i == 0:
            lin.weight[:, 3:] = 0.0
    w = out.weight
    torch.nn.init.normal_(w, 0.0, 1e-4)
    torch.nn.init.normal_(w[:1], math.sqrt(math.pi) / math.sqrt(w.shape[1]), 1e-4)
    torch.nn.init.zeros_(out.bias)
    out.bias[0] = -radius

@MODELS.register("sdf_field")
class SDFField(torch.nn.Module):
    """An :class:`SDFNetwork` and a :class:`ColorNetwork` sharing the SDF features.

    ``forward(points (N, 3), dirs (N, 3)) -> (sdf (N,), rgb (N, 3))``; ``sdf(points)`` alone.
    ``sdf_net`` / ``color_net`` hold the keyword arguments of each part.
    """

    def __init__(self, scene_box=None, sdf_net: Optional[dict] = None, color_net: Optional[dict] = None):
        super().__init__()
        sdf_kw = dict(sdf_net or {})
        self.sdf_net = SDFNetwork(scene_box=scene_box, **sdf_kw)
        self.color_net = ColorNetwork(n_features=self.sdf_net.n_features, **dict(color_net or {}))

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        return self.sdf_net.sdf(points)

    def forward(self, points: torch.Tensor, dirs: Optional[torch.Tensor] = None
                ) -> Tuple[torch.Tensor, torch.Tensor]:
        f, feat = self.sdf_net(points)
        return f, self.color_net(points, feat, dirs)


def fit_to_sphere(sdf_fn: Callable[[torch.Tensor], torch.Tensor], params: Iterable[torch.nn.Parameter],
                  radius: float, bounds: Tuple[Sequence[float], Sequence[float]], steps: int = 200,
                  n_points: int = 2048, lr: float = 1e-3, generator: Optional[torch.Generator] = None,
                  device=None) -> float:
    """Fit ``params`` so that ``sdf_fn(x (N, 3)) -> (N,)`` matches the sphere SDF ``|x| - radius``
    on uniform points in ``bounds`` (Adam, L1); returns the final mean absolute error (world units)."""
    lo = torch.as_tensor(bounds[0], dtype=torch.float32, device=device)
    hi = torch.as_tensor(bounds[1], dtype=torch.float32, device=device)
    opt = torch.optim.Adam(params, lr=lr)
    err = float("nan")
    for _ in range(int(steps)):
        u = torch.rand(n_points, 3, generator=generator)          # CPU draw (the run's one generator), then moved
        x = lo + u.to(lo.device) * (hi - lo)
        loss = (sdf_fn(x) - (x.norm(dim=-1) - radius)).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        err = float(loss.detach())
    return err


def pretrain_sphere(net: SDFNetwork, radius: float, bounds: Tuple[Sequence[float], Sequence[float]],
                    steps: int = 200, n_points: int = 2048, lr: float = 1e-3,
                    generator: Optional[torch.Generator] = None) -> float:
    """Fit ``net`` to the sphere SDF ``|x| - radius`` (see :func:`fit_to_sphere`)."""
    return fit_to_sphere(lambda x: net(x)[0], net.parameters(), radius, bounds, steps, n_points, lr,
                         generator, device=next(net.parameters()).device)
