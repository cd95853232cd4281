"""Trilinear lookup in a dense grid stored as a table of cells, with a sparse gradient.

A level of :class:`~nepf_core.fields.grid_encoding.MultiResGrid` is a table ``V [R^3, F]``
(node ``(i, j, k)`` along ``(x, y, z)`` is row ``(k R + j) R + i``). A point ``x [N, 3]`` in
``[-bound, bound]^3`` has the continuous node coordinate

    u = clip((x / bound + 1) / 2 * (R - 1), 0, R - 1)         (align_corners=True, border padding)

its cell's lower node ``i0 = min(floor(u), R - 2)``, fraction ``f = u - i0`` in ``[0, 1]``, and

    out(x) = sum_{c in {0,1}^3} prod_a (c_a f_a + (1 - c_a)(1 - f_a)) V[i0 + c]      [N, F]

which is ``F.grid_sample(V as [1, F, R, R, R], x / bound, "bilinear", "border",
align_corners=True)`` (same value; float rounding aside).

Why not ``grid_sample``: its backward returns a gradient the size of the whole level, zero
filled, for every call, which autograd then adds into ``.grad``. A `fast` step looks the SDF up
~18 times (samples, the finite-difference stencil, eikonal points, the zero-crossing refinement,
the surface-point prior), so that zeroing and adding were half of a step on the CPU
(docs/FAST.md, "Where a step's time goes"). Here the backward scatter-adds the rows it read
straight into ``table.grad`` (``index_add_``; the buffer is allocated and zeroed once per
backward, when ``.grad`` is None after ``zero_grad(set_to_none=True)``). Autograd's own sparse
gradients (``embedding_bag(sparse=True)``) were measured too: the engine sums the calls' sparse
gradients by concatenating them, pairwise, which cost more than the dense fills (docs/TRIED.md).

The price: the table's gradient does not travel through autograd. ``loss.backward()`` fills
``table.grad`` as usual, but ``torch.autograd.grad(out, table)`` returns None, and a backward
taken only for ``x`` still adds into ``table.grad`` (zero it before the backward you step on,
as ``fit()`` does). The gradient with respect to ``x`` flows through the corner weights and is
zero where ``x`` is clipped, as in ``grid_sample``'s border mode.

Device-agnostic: ``embedding_bag`` and ``index_add_`` run on CUDA as on the CPU.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["corner_rows_and_weights", "trilinear_lookup"]

# the 8 corners of a cell as (dx, dy, dz), x fastest
_CORNERS = ((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1), (1, 1, 1))


def corner_rows_and_weights(x: Tensor, resolutions: Tensor, first_rows: Tensor, bound: float) -> tuple[Tensor, Tensor]:
    """Rows and weights of the 8 nodes around each point in each of ``L`` levels (module docstring).

    ``x [N, 3]``; ``resolutions [L]`` (``R_l``, int64, >= 2); ``first_rows [L]`` (the table row of
    level ``l``'s node ``(0, 0, 0)``) -> ``(rows [N, L, 8] int64, weights [N, L, 8])``, the weights
    in ``x``'s dtype, summing to 1 per point and level, differentiable in ``x``."""
    r = resolutions.to(x.dtype)                                          # [L]
    u = (x[:, None, :] / bound + 1.0) * (0.5 * (r - 1.0))[None, :, None]   # [N, L, 3]
    u = torch.minimum(u.clamp_min(0.0), (r - 1.0)[None, :, None])
    i0 = torch.minimum(u.detach().floor(), (r - 2.0)[None, :, None])      # lower node
    f = u - i0                                                             # [N, L, 3] in [0, 1]
    i0 = i0.long()
    rl = resolutions[None, :]
    base = (i0[..., 2] * rl + i0[..., 1]) * rl + i0[..., 0] + first_rows[None, :]   # [N, L]
    d = torch.tensor(_CORNERS, device=x.device)                           # [8, 3]
    offsets = (d[None, :, 2] * resolutions[:, None] + d[None, :, 1]) * resolutions[:, None] + d[None, :, 0]   # [L, 8]
    rows = base[..., None] + offsets                                       # [N, L, 8]
    g = 1.0 - f
    wx = torch.stack([g[..., 0], f[..., 0]], -1)                           # [N, L, 2]
    wy = torch.stack([g[..., 1], f[..., 1]], -1)
    wz = torch.stack([g[..., 2], f[..., 2]], -1)
    w = (wz[..., :, None, None] * wy[..., None, :, None] * wx[..., None, None, :]).flatten(-3)   # [N, L, 8], x fastest
    return rows, w


def _zeroed_grad_buffer(table: Tensor) -> Tensor:
    """A zeroed ``[rows, F]`` gradient for ``table``, reusing the memory of the last one: a
    fresh multi-megabyte allocation each step comes from the OS page by page (page faults that
    cost ~10x the zero fill itself)."""
    buf = getattr(table, "_grad_buffer", None)
    if buf is None or buf.shape != table.shape or buf.dtype != table.dtype or buf.device != table.device:
        buf = table._grad_buffer = torch.zeros_like(table)
    else:
        buf.zero_()
    return buf


class _TableLookup(torch.autograd.Function):
    """``out[b] = sum_c w[b, c] table[rows[b, c]]`` for bags ``b``; the table's gradient is
    scattered into ``table.grad`` in place (module docstring), ``w``'s is returned."""

    @staticmethod
    def forward(ctx, table: Tensor, rows: Tensor, w: Tensor) -> Tensor:
        ctx.table = table
        ctx.save_for_backward(rows, w)
        return F.embedding_bag(rows, table.detach(), per_sample_weights=w.detach(), mode="sum")

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        rows, w = ctx.saved_tensors
        table = ctx.table
        n_feat = table.shape[1]
        if ctx.needs_input_grad[0]:
            if table.grad is None:
                table.grad = _zeroed_grad_buffer(table)
            flat = (rows[:, :, None] * n_feat + torch.arange(n_feat, device=rows.device)).reshape(-1)   # [B*8*F]
            table.grad.view(-1).index_add_(0, flat, (w[:, :, None] * grad_out[:, None, :]).reshape(-1))
        grad_w = None
        if ctx.needs_input_grad[2]:
            grad_w = (table.detach()[rows] * grad_out[:, None, :]).sum(-1)                              # [B, 8]
        return None, None, grad_w


def trilinear_lookup(table: Tensor, x: Tensor, resolutions: Tensor, first_rows: Tensor, bound: float) -> Tensor:
    """``table [sum_l R_l^3, F]`` (the levels' tables stacked), ``x [N, 3]`` -> ``[N, L, F]``:
    the trilinear interpolation of the module docstring in each level, in one lookup; the table's
    gradient goes into ``table.grad`` (rows read only), ``x``'s through autograd."""
    rows, w = corner_rows_and_weights(x.to(table.dtype), resolutions, first_rows, bound)
    n, n_levels = rows.shape[:2]
    rows, w = rows.reshape(n * n_levels, 8), w.reshape(n * n_levels, 8)
    if torch.is_grad_enabled() and (table.requires_grad or w.requires_grad):
        out = _TableLookup.apply(table, rows, w)
    else:
        out = F.embedding_bag(rows, table, per_sample_weights=w, mode="sum")
    return out.reshape(n, n_levels, -1)
