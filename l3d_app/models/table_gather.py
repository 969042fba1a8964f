"""Rows of a parameter table gathered by index, with a backward that accumulates fast on CPU.

The grid encodings read ``8 x N x L`` table rows per call (8 corners, N points, L levels);
autograd's backward of ``index_select`` is ``index_add_``, which on CPU adds one row at a
time: 11% of a volsdf training step's CPU time in a profile, and several times slower than
``torch.bincount`` with weights on the same rows (``python bench/bench_table_gather.py``,
docs/cpu_frontier.md). :func:`gather_rows` gathers like ``index_select`` and, on CPU,
accumulates the rows' gradients with one weighted ``bincount`` per feature column (in the
table's dtype, like ``index_add_``); on other devices it keeps ``index_add_`` (atomic adds).
"""

from __future__ import annotations

import torch


class _GatherRows(torch.autograd.Function):
    """``table[index]`` for a 2-D table (T, F) and a 1-D long index (M,) -> (M, F)."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(index)
        ctx.rows, ctx.dtype = table.shape[0], table.dtype
        return table.index_select(0, index)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        (index,) = ctx.saved_tensors
        return scatter_rows(grad_out.to(ctx.dtype), index, ctx.rows), None


def scatter_rows(values: torch.Tensor, index: torch.Tensor, rows: int) -> torch.Tensor:
    """(rows, F) table whose row r is the sum of ``values[m]`` (M, F) over ``index[m] == r``."""
    if values.device.type != "cpu":
        return values.new_zeros(rows, values.shape[1]).index_add_(0, index, values)
    cols = [torch.bincount(index, weights=values[:, f], minlength=rows) for f in range(values.shape[1])]
    return torch.stack(cols, dim=1)


def gather_rows(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``table.index_select(0, index)``: (T, F) table, (M,) long index -> (M, F); differentiable
    w.r.t. ``table`` (its gradient accumulated by :func:`scatter_rows`), not w.r.t. the index."""
    if not table.requires_grad or not torch.is_grad_enabled():
        return table.index_select(0, index)
    return _GatherRows.apply(table, index)
