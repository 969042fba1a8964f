"""Fast neural SDF: multi-resolution grid encoding + small MLP, with its exact spatial gradient.

:class:`SDFGridField` (``model=sdf_grid_field``, the volsdf default) is the Instant-NSR /
Neuralangelo recipe in pure PyTorch:

* **SDF** ``f(x) = MLP([x, grid(x)])`` -- :class:`~l3d_app.models.encodings.GridEncoding` over
  the scene box (table initialised near zero) concatenated with ``x``, ``n_layers`` Softplus
  (beta=100) layers, a linear output ``[f, features]`` without activation.
* **Sphere initialisation that works with the grid**: geometric init of the MLP on ``x``
  (SAL / NeuS rule: hidden weights ``N(0, 2/width)``, SDF row ``N(sqrt(pi/width), 1e-4)``,
  bias ``-radius``) with the grid's input columns set to 0, so at step 0 the field is a
  sphere whatever the (near-zero) table holds; :meth:`SDFGridField.pretrain_sphere` then
  fits the MLP alone (the grid is not involved, it stays near zero) to ``|x| - radius``.
* **Exact gradient without double backward**: :func:`grid_encode_with_jacobian` returns the
  trilinear features AND their spatial Jacobian from one table gather (the derivative of a
  trilinear weight is a product of two weights times the level's cells per unit); the
  MLP's row ``d f / d h`` is taken back through its layers (matrix products, ``f`` being one
  scalar per point) and contracted with that Jacobian. ``grad f`` is then an ordinary
  differentiable expression: the eikonal loss and normal-conditioned colour backpropagate
  with one first-order backward (autograd's create_graph path through the hashed gather is
  about twice as slow on CPU).
* **Coarse-to-fine**: only the first ``active_levels`` grid levels feed the MLP (the others
  are multiplied by 0); the task raises it during training (Neuralangelo's progressive levels).
* **Colour** ``rgb = sigmoid(MLP([x, n, d, features]))`` with the unit normal ``n = grad f /
  |grad f|``, the view direction ``d`` (optional) and the SDF features.

``forward(points, dirs) -> (sdf (N,), rgb (N, 3))`` like :class:`~l3d_app.models.sdf_net.SDFField`;
``sdf(points) -> (...)``; ``sdf_rgb_grad(points, dirs) -> (sdf, rgb, grad (N, 3))``.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.models.encodings import GridEncoding
from l3d_app.models.sdf_net import fit_to_sphere, geometric_init
from l3d_app.models.table_gather import gather_rows
from l3d_app.registry import MODELS


def grid_encode_with_jacobian(enc: GridEncoding, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Features (N, L*F) of ``enc`` at x (N, 3) and their spatial Jacobian (N, L*F, 3) (per
    world unit), both differentiable w.r.t. the table, from ONE gather of the 8 corners.

    Trilinear interpolation as nested lerps (z, then y, then x); the derivative along an axis
    is the difference of the two lerped faces across it, lerped along the remaining axes,
    times the level's cells per world unit. Outside the box (where the encoding clamps) the
    Jacobian is 0. The features equal ``enc(x)`` up to rounding.
    """
    idx, _ = enc.corner_indices_and_weights(x)                                     # (8, N, L)
    lo, hi = enc.lo.to(x.dtype), enc.hi.to(x.dtype)
    u = (x - lo) / (hi - lo)
    res = enc.resolution
    pos = u.clamp(0.0, 1.0)[:, :, None] * (res - 1).to(x.dtype)                      # (N, 3, L)
    frac = (pos - torch.minimum(pos.floor(), (res - 2).to(x.dtype)))[..., None]      # (N, 3, L, 1)
    fx, fy, fz = frac[:, 0], frac[:, 1], frac[:, 2]                                  # (N, L, 1)
    c = gather_rows(enc.table, idx.reshape(-1)).view(2, 2, 2, *idx.shape[1:], enc.n_features)
    # unbind, not indexing: the backward of each index would zero-fill a tensor of c's size
    cz0, cz1 = c.unbind(2)                                                           # (2, 2, N, L, F)
    dz = cz1 - cz0
    cy0, cy1 = (cz0 + fz * dz).unbind(1)                                             # (2, N, L, F)
    dy = cy1 - cy0
    dz0, dz1 = dz.unbind(1)
    dzy0, dzy1 = (dz0 + fy * (dz1 - dz0)).unbind(0)                                  # (N, L, F)
    cx0, cx1 = (cy0 + fy * dy).unbind(0)
    dx = cx1 - cx0
    dy0, dy1 = dy.unbind(0)
    value = cx0 + fx * dx
    jac = torch.stack([dx, dy0 + fx * (dy1 - dy0), dzy0 + fx * (dzy1 - dzy0)], dim=-1)  # (N, L, F, 3)
    inside = ((u >= 0) & (u <= 1)).to(x.dtype)                                       # (N, 3)
    scale = (res - 1).to(x.dtype)[:, None] / (hi - lo)[None, :]                      # (L, 3)
    jac = jac * (scale[None, :, None, :] * inside[:, None, None, :])
    return value.reshape(x.shape[0], enc.out_dim), jac.reshape(x.shape[0], enc.out_dim, 3)


class _Softplus100(torch.nn.Module):
    """Softplus(beta) and its derivative sigmoid(beta z) (for the forward-mode Jacobian)."""

    def __init__(self, beta: float):
        super().__init__()
        self.beta = float(beta)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.softplus(z, beta=self.beta)

    def derivative(self, z: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.beta * z)


@MODELS.register("sdf_grid_field")
class SDFGridField(torch.nn.Module):
    """Grid-encoded SDF + normal/view-conditioned colour (see the module docstring).

    Args:
        scene_box: ((x0, y0, z0), (x1, y1, z1)) world box of the grid (required).
        n_levels, n_features, base_resolution, max_resolution, log2_hashmap_size, init_scale:
            :class:`GridEncoding` (``init_scale``: table uniform in +-init_scale, near 0).
        hidden, n_layers: SDF MLP width / hidden layers; sdf_features: features passed on.
        radius: the initial sphere (world units).
        color_hidden, color_layers: colour MLP (ReLU); use_normals / use_viewdirs: inputs.
        softplus_beta: sharpness of the SDF MLP's Softplus.
    """

    def __init__(self, scene_box=None, n_levels: int = 8, n_features: int = 2, base_resolution: int = 16,
                 max_resolution: int = 128, log2_hashmap_size: int = 17, init_scale: float = 1e-4,
                 hidden: int = 64, n_layers: int = 1, sdf_features: int = 15, radius: float = 0.85,
                 color_hidden: int = 64, color_layers: int = 2, use_normals: bool = True,
                 use_viewdirs: bool = True, softplus_beta: float = 100.0):
        super().__init__()
        if scene_box is None:
            raise UserError("sdf_grid_field needs the scene box (the data source provides it)")
        if int(n_layers) < 1 or int(hidden) < 1 or int(color_layers) < 0:
            raise UserError(f"sdf_grid_field needs n_layers >= 1, hidden >= 1, color_layers >= 0, "
                            f"got {n_layers}, {hidden}, {color_layers}")
        if not float(radius) > 0:
            raise UserError(f"sdf_grid_field needs radius > 0 (world units), got {radius}")
        self.encoding = GridEncoding(n_levels, n_features, base_resolution, max_resolution, log2_hashmap_size,
                                     bounds=scene_box, init_scale=init_scale)
        self.radius, self.n_features = float(radius), int(sdf_features)
        self.use_normals, self.use_viewdirs = bool(use_normals), bool(use_viewdirs)
        dims = [3 + self.encoding.out_dim] + [int(hidden)] * int(n_layers)
        self.layers = torch.nn.ModuleList(torch.nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.out = torch.nn.Linear(dims[-1], 1 + self.n_features)
        self.act = _Softplus100(softplus_beta)
        d = 3 + 3 * self.use_normals + 3 * self.use_viewdirs + self.n_features
        layers = []
        for _ in range(int(color_layers)):
            layers += [torch.nn.Linear(d, int(color_hidden)), torch.nn.ReLU()]
            d = int(color_hidden)
        layers.append(torch.nn.Linear(d, 3))
        self.color = torch.nn.Sequential(*layers)
        self.register_buffer("level_mask", torch.ones(self.encoding.n_levels), persistent=True)
        geometric_init(self.layers, self.out, self.radius)

    # ------------------------------------------------------------------ init / levels
    def mlp_parameters(self):
        """The SDF MLP's parameters (what :meth:`pretrain_sphere` fits)."""
        return list(self.layers.parameters()) + list(self.out.parameters())

    def set_active_levels(self, n: int) -> None:
        """Use the first ``n`` grid levels (1 .. n_levels), the finer ones are masked to 0."""
        n = max(1, min(int(n), self.encoding.n_levels))
        self.level_mask.copy_((torch.arange(self.encoding.n_levels, device=self.level_mask.device) < n).float())

    @property
    def active_levels(self) -> int:
        return int(self.level_mask.sum())

    def pretrain_sphere(self, bounds, steps: int = 200, n_points: int = 4096, lr: float = 1e-3,
                        generator: Optional[torch.Generator] = None) -> float:
        """Fit the MLP (the grid is fed zeros and not trained) to ``|x| - radius`` on uniform
        points in ``bounds`` (Adam, L1); returns the final mean absolute error (world units)."""
        device = self.out.weight.device

        def mlp_sdf(x: torch.Tensor) -> torch.Tensor:
            zeros = torch.zeros(x.shape[0], self.encoding.out_dim, device=device)
            return self._mlp(torch.cat([x, zeros], dim=-1))[..., 0]

        return fit_to_sphere(mlp_sdf, self.mlp_parameters(), self.radius, bounds, steps, n_points, lr,
                             generator, device=device)

    # ------------------------------------------------------------------ SDF
    def _mask(self) -> torch.Tensor:
        return self.level_mask.repeat_interleave(self.encoding.n_features)

    def _mlp(self, h: torch.Tensor) -> torch.Tensor:
        for lin in self.layers:
            h = self.act(lin(h))
        return self.out(h)

    def sdf_features(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """x (N, 3) -> SDF (N,) world units, features (N, sdf_features)."""
        h = torch.cat([x, self.encoding(x) * self._mask()], dim=-1)
        out = self._mlp(h)
        return out[..., 0], out[..., 1:]

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """points (..., 3) -> SDF (...)."""
        return self.sdf_features(points.reshape(-1, 3))[0].reshape(points.shape[:-1])

    def sdf_features_gradient(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SDF (N,), features (N, F) and ``grad f`` (N, 3) at x (N, 3), all differentiable
        w.r.t. the parameters (exact: :func:`grid_encode_with_jacobian` through the MLP)."""
        mask = self._mask()
        enc, jac = grid_encode_with_jacobian(self.encoding, x)
        h = torch.cat([x, enc * mask], dim=-1)                                        # (N, D)
        pre = []
        for lin in self.layers:
            pre.append(lin(h))
            h = self.act(pre[-1])
        out = self.out(h)
        # grad f = d f / d x by the chain rule taken from the output back (f is a scalar per point):
        # v = w_f diag(act'(z_L)) W_L ... diag(act'(z_1)) W_1, a (N, D) row per point from mm's,
        # then grad = v_x + v_enc J_enc; the same products as pushing the (N, D, 3) Jacobian forward
        v = self.out.weight[0].expand(x.shape[0], -1)                                 # (N, H)
        for lin, z in zip(reversed(self.layers), reversed(pre)):
            v = (v * self.act.derivative(z)) @ lin.weight                             # (N, D_in)
        grad = v[:, :3] + ((v[:, 3:] * mask)[:, :, None] * jac).sum(dim=1)
        return out[..., 0], out[..., 1:], grad

    # ------------------------------------------------------------------ colour
    def rgb(self, x: torch.Tensor, grad: Optional[torch.Tensor], dirs: Optional[torch.Tensor],
            features: torch.Tensor) -> torch.Tensor:
        """(N, 3) colour in [0, 1] from position, normal (from ``grad``), view direction, features."""
        parts = [x]
        if self.use_normals:
            parts.append(grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-6))
        if self.use_viewdirs:
            if dirs is None:
                raise UserError("this sdf_grid_field uses view directions: pass dirs")
            parts.append(dirs)
        parts.append(features)
        return torch.sigmoid(self.color(torch.cat(parts, dim=-1)))

    def sdf_rgb_grad(self, points: torch.Tensor, dirs: Optional[torch.Tensor] = None
                     ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """points, dirs (N, 3) -> SDF (N,), rgb (N, 3), grad f (N, 3) (all differentiable)."""
        f, feat, grad = self.sdf_features_gradient(points)
        return f, self.rgb(points, grad, dirs, feat), grad

    def forward(self, points: torch.Tensor, dirs: Optional[torch.Tensor] = None
                ) -> Tuple[torch.Tensor, torch.Tensor]:
        """points, dirs (N, 3) -> SDF (N,), rgb (N, 3)."""
        f, rgb, _ = self.sdf_rgb_grad(points, dirs)
        return f, rgb


def pretrain_field(field: torch.nn.Module, bounds: Tuple[Sequence[float], Sequence[float]], steps: int,
                   generator: Optional[torch.Generator] = None) -> float:
    """Sphere pretraining of either SDF model to its own initial sphere (grid field: MLP only; MLP field
    (:class:`~l3d_app.models.sdf_net.SDFField`): the SDF net); the final mean ``|f - sdf_sphere|`` (world units)."""
    if isinstance(field, SDFGridField):
        return field.pretrain_sphere(bounds, steps=steps, generator=generator)
    from l3d_app.models.sdf_net import pretrain_sphere

    return pretrain_sphere(field.sdf_net, field.sdf_net.radius, bounds, steps=steps, generator=generator)
