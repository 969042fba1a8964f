"""Parameter surgery shared by strategies: append / keep rows, reset Adam moments of rows.

A resized tensor becomes a NEW ``torch.nn.Parameter`` (autograd caches leaf shapes), swapped
into the model and into the optimiser's param group, with its Adam moments carried over
(zeros for new rows). A list of parameters taken before a resize goes stale.
"""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.models.gaussians import PARAM_NAMES

ADAM_MOMENTS = ("exp_avg", "exp_avg_sq")


def replace_rows(model, optimizer: torch.optim.Optimizer, added: Dict[str, torch.Tensor],
                 keep: torch.Tensor) -> None:
    """Append ``added[name]`` (M, ...) rows to each parameter, then keep rows ``keep`` (N + M,) bool."""
    for name in PARAM_NAMES:
        p = getattr(model, name)
        q = torch.nn.Parameter(torch.cat([p.data, added[name].to(p.dtype)])[keep].contiguous())
        st = optimizer.state.pop(p, None)
        if st:
            for k in ADAM_MOMENTS:
                if k in st:
                    v = st[k]
                    st[k] = torch.cat([v, torch.zeros((added[name].shape[0], *v.shape[1:]), dtype=v.dtype,
                                                      device=v.device)])[keep].contiguous()
            optimizer.state[q] = st
        for g in optimizer.param_groups:
            g["params"] = [q if x is p else x for x in g["params"]]
        setattr(model, name, q)


def append_rows(model, optimizer: torch.optim.Optimizer, added: Dict[str, torch.Tensor]) -> None:
    """Append rows (zero Adam moments for them), keeping every existing row."""
    n, m = model.num, next(iter(added.values())).shape[0]
    replace_rows(model, optimizer, added, torch.ones(n + m, dtype=torch.bool, device=model.means.device))


def zero_moments(optimizer: torch.optim.Optimizer, param: torch.Tensor, rows: torch.Tensor) -> None:
    """Zero the Adam moments of ``param`` at ``rows`` (indices or bool mask); all rows if None."""
    st = optimizer.state.get(param, {})
    for k in ADAM_MOMENTS:
        if k in st:
            if rows is None:
                st[k].zero_()
            else:
                st[k][rows] = 0
