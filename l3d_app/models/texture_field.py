"""A texture *field*: RGB as a function of the surface point, so a texture has no UV seams
and its resolution does not depend on the mesh's vertex density (used by ``sds_mesh``)."""

from __future__ import annotations

import torch

from l3d_app.errors import UserError
from l3d_app.models.encodings import HarmonicEncoding


class TextureField(torch.nn.Module):
    """Surface point (N, 3) world units -> RGB (N, 3) in (0, 1).

    ``harmonic(p)`` with ``n_frequencies`` octaves -> ``layers`` ReLU layers of ``hidden``
    -> sigmoid. The output layer starts at zero, so the initial texture is uniform grey 0.5.
    """

    def __init__(self, n_frequencies: int = 4, hidden: int = 64, layers: int = 2):
        super().__init__()
        if hidden < 1 or layers < 1:
            raise UserError(f"texture field needs hidden >= 1 and layers >= 1, got {hidden}, {layers}")
        self.encoding = HarmonicEncoding(3, n_frequencies)
        mods, d = [], self.encoding.out_dim
        for _ in range(int(layers)):
            mods += [torch.nn.Linear(d, hidden), torch.nn.ReLU()]
            d = hidden
        head = torch.nn.Linear(d, 3)
        torch.nn.init.zeros_(head.weight)
        torch.nn.init.zeros_(head.bias)
        self.mlp = torch.nn.Sequential(*mods, head)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.mlp(self.encoding(points)))
