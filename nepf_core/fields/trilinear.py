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

__all__ = ["LevelLayout", "corner_rows_and_weights", "trilinear_lookup"]

# the 8 corners of a cell as (dx, dy, dz), x fastest
_CORNERS = ((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1), (1, 1, 1))


class LevelLayout:
    """Per-level constants of the lookup, cached per (levels, dtype, device) so that they follow
    the inputs: resolutions ``[L]``, the table row of each level's node ``(0, 0, 0)``, the row
    offsets of a cell's 8 corners ``[8, L]``."""

    def __init__(self, resolutions: list[int], first_rows: list[int]) -> None:
        self.resolutions, self.first_rows = list(resolutions), list(first_rows)
        self.n_rows = first_rows[-1] + resolutions[-1] ** 3
        self._cache: dict = {}

    def constants(self, n_levels: int, dtype: torch.dtype, device: torch.device) -> dict:
        key = (n_levels, dtype, device)
        if key not in self._cache:
            # integer row arithmetic in floating point is exact below 2^24 rows (fp32) / 2^53 (fp64)
            ft = torch.float32 if self.n_rows < 2 ** 24 else torch.float64
            r = torch.tensor(self.resolutions[:n_levels], dtype=ft, device=device)                    # [L]
            corners = torch.tensor(_CORNERS, dtype=ft, device=device)                                 # [8, 3]
            stride = torch.stack([torch.ones_like(r), r, r * r], -1)                                 # [L, 3]
            self._cache[key] = {
                "half_span": (0.5 * (r - 1.0))[:, None].to(dtype),                                   # [L, 1]
                "hi": (r - 1.0)[:, None].expand(-1, 3).to(dtype).contiguous(),                       # [L, 3]
                "hi_cell": (r - 2.0)[:, None].expand(-1, 3).to(dtype).contiguous(),                  # [L, 3]
                "stride": stride, "first": torch.tensor(self.first_rows[:n_levels], dtype=ft, device=device),
                "corner_offsets": corners @ stride.t(),                                              # [8, L]
            }
        return self._cache[key]


def corner_rows_and_weights(x: Tensor, layout: LevelLayout, n_levels: int, bound: float) -> tuple[Tensor, Tensor]:
    """Rows and weights of the 8 nodes around each point in the first ``n_levels`` levels.

    ``x [N, 3]`` -> ``(rows [N, L, 8] int64, weights [N, L, 8])``, the weights in ``x``'s dtype,
    summing to 1 per point and level, differentiable in ``x``; corners ordered x fastest."""
    c = layout.constants(n_levels, x.dtype, x.device)
    half = c["half_span"]
    u = torch.addcmul(half, x[:, None, :], half / bound)                   # (x/b + 1)(R-1)/2   [N, L, 3]
    u = torch.clamp(u, torch.zeros_like(c["hi"]), c["hi"])
    i0 = torch.minimum(u.detach().floor(), c["hi_cell"])                  # the cell's lower node
    f = u - i0                                                             # [N, L, 3] in [0, 1]
    base = (i0.to(c["stride"].dtype) * c["stride"]).sum(-1) + c["first"]   # [N, L]
    rows = (base[..., None] + c["corner_offsets"].t()).long()             # [N, L, 8]
    g = 1.0 - f
    fx, fy, fz, gx, gy, gz = f[..., 0], f[..., 1], f[..., 2], g[..., 0], g[..., 1], g[..., 2]
    wxy = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], -1)            # [N, L, 4]
    w = torch.cat([wxy * gz[..., None], wxy * fz[..., None]], -1)          # [N, L, 8]
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
            table.grad.index_add_(0, rows.reshape(-1), (w[:, :, None] * grad_out[:, None, :]).reshape(-1, n_feat))
        grad_w = None
        if ctx.needs_input_grad[2]:
            grad_w = (table.detach()[rows] * grad_out[:, None, :]).sum(-1)                              # [B, 8]
        return None, None, grad_w


def trilinear_lookup(table: Tensor, x: Tensor, layout: LevelLayout, n_levels: int, bound: float) -> Tensor:
    """``table [sum_l R_l^3, F]`` (the levels' tables stacked), ``x [N, 3]`` -> ``[N, L, F]``:
    the trilinear interpolation of the module docstring in each level, in one lookup; the table's
    gradient goes into ``table.grad`` (rows read only), ``x``'s through autograd."""
    rows, w = corner_rows_and_weights(x.to(table.dtype), layout, n_levels, bound)
    n, n_levels = rows.shape[:2]
    rows, w = rows.reshape(n * n_levels, 8), w.reshape(n * n_levels, 8)
    if torch.is_grad_enabled() and (table.requires_grad or w.requires_grad):
        out = _TableLookup.apply(table, rows, w)
    else:
        out = F.embedding_bag(rows, table, per_sample_weights=w, mode="sum")
    return out.reshape(n, n_levels, -1)
