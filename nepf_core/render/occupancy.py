"""SDF-driven occupancy grid (the `fast` preset): which rays meet no occupied cell.

Occupancy rule (never culls the surface, given the stated assumptions)
---------------------------------------------------------------------
Cells are the ``R^3`` cubes of side ``h = 2*bound/R`` tiling ``[-bound, bound]^3``, with
centres ``c``. :meth:`OccupancyGrid.ray_hits` marches each ray in segments of length ``<= delta`` (the march
step, ``delta = march_ratio * h``) and looks up the cell of each segment's *midpoint* ``m``.
Every point ``p`` of the segment satisfies ``|p - c| <= |p - m| + |m - c| <= delta/2 + r_h``
with ``r_h = sqrt(3) h / 2`` the cell half-diagonal. If the SDF is ``L``-Lipschitz
(``|grad f| <= L``) and the zero level set meets the segment at ``p``, then
``|f(c)| <= L (r_h + delta/2)``. So a cell is marked occupied iff

    |f(c)| <= safety * (r_h + delta/2) + k_s / inv_s                       (1)

and, with ``safety >= L``, a march segment that contains surface is never skipped; in
particular every cell the surface passes through is occupied. ``safety`` (default 1.5)
covers learned SDFs that are only approximately eikonal (|grad f| ~ 1 +- 0.3 is typical
mid-training) and the SDF moving between updates. The ``k_s / inv_s`` term keeps NeuS's
density band: where ``|f| > k_s / s`` the logistic CDF is within ``e^{-k_s}`` of 0 or 1,
so the opacity a skipped region could contribute is ``<= ~e^{-k_s}`` (k_s = 6: 0.25 %).
Early in training ``inv_s`` is small and (1) keeps most of the object's neighbourhood.

Space outside ``[-bound, bound]^3`` is treated as empty (the object is inside the unit
sphere in the normalised frame).

Updates
-------
``update(sdf_fn, inv_s, step, fraction)`` evaluates ``|f|`` at all (or a random
``fraction`` of the) cell centres in chunks under ``no_grad``. With a subset, the stored
``|f|`` of the cells *not* evaluated is multiplied by ``stale_decay < 1`` first, so staleness
can only turn cells occupied, never cull them. Before the first update every cell is
occupied.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["OccupancyConfig", "OccupancyGrid", "ray_aabb"]


@dataclass
class OccupancyConfig:
    """Configuration of :class:`OccupancyGrid`."""

    resolution: int = 64
    """Cells per axis (R); memory R^3 floats + R^3 bools."""
    bound: float = 1.0
    """The grid covers ``[-bound, bound]^3``; outside is empty."""
    safety: float = 1.5
    """Assumed Lipschitz bound of the learned SDF in rule (1) (>= 1; 1 is exact for a true SDF)."""
    k_s: float = 6.0
    """NeuS band half-width in units of 1/inv_s (opacity skipped <= ~exp(-k_s))."""
    march_ratio: float = 0.5
    """March step as a fraction of the cell size (smaller: tighter band, more lookups)."""
    stale_decay: float = 0.8
    """With partial updates, |f| of cells not re-evaluated is multiplied by this."""
    dilation: int = 0
    """Extra dilation of the occupied set by this many cells (max-pool), on top of (1)."""
    chunk: int = 65536
    """Cell centres per SDF call during an update."""


def ray_aabb(rays_o: Tensor, rays_d: Tensor, bound: float) -> tuple[Tensor, Tensor]:
    """Slab test against ``[-bound, bound]^3``: ``(t_in [B], t_out [B])``; miss iff ``t_out <= t_in``.

    ``t_in = max_a min(t_a-, t_a+)``, ``t_out = min_a max(t_a-, t_a+)`` with
    ``t_a+- = (+-bound - o_a) / d_a`` (``d_a = 0`` handled by a tiny epsilon).
    """
    d = torch.where(rays_d.abs() < 1e-12, torch.full_like(rays_d, 1e-12), rays_d)
    inv = 1.0 / d
    t_lo = (-bound - rays_o) * inv
    t_hi = (bound - rays_o) * inv
    t_in = torch.minimum(t_lo, t_hi).amax(-1)
    t_out = torch.maximum(t_lo, t_hi).amin(-1)
    return t_in, t_out


class OccupancyGrid(nn.Module):
    """Binary occupancy over ``[-bound, bound]^3`` from an SDF, and the rays that meet it.

    Buffers (move with ``.to()``, saved in ``state_dict``):
    ``sdf_abs [R^3]`` float (last |f| at cell centres, 0 = never evaluated) and
    ``occ [R,R,R]`` bool indexed ``[ix, iy, iz]`` (cell ``i`` spans
    ``[-bound + i h, -bound + (i+1) h]`` on each axis, ``h = 2 bound / R``).
    """

    def __init__(self, cfg: OccupancyConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or OccupancyConfig()
        r = cfg.resolution
        self.register_buffer("sdf_abs", torch.zeros(r**3))
        self.register_buffer("occ", torch.ones(r, r, r, dtype=torch.bool))
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.long))

    # -- geometry -------------------------------------------------------------------
    @property
    def cell_size(self) -> float:
        """``h = 2 bound / R``."""
        return 2.0 * self.cfg.bound / self.cfg.resolution

    @property
    def march_step(self) -> float:
        """Max march segment length ``delta = march_ratio * h``."""
        return self.cfg.march_ratio * self.cell_size

    def threshold(self, inv_s: float) -> float:
        """Rule (1): ``safety * (sqrt(3) h / 2 + delta / 2) + k_s / inv_s``."""
        half_diag = math.sqrt(3.0) * 0.5 * self.cell_size
        return self.cfg.safety * (half_diag + 0.5 * self.march_step) + self.cfg.k_s / float(inv_s)

    def cell_centres(self, flat_idx: Tensor) -> Tensor:
        """Centres ``[M,3]`` of cells with flat index ``(ix*R + iy)*R + iz``."""
        r = self.cfg.resolution
        iz = flat_idx % r
        iy = (flat_idx // r) % r
        ix = flat_idx // (r * r)
        ijk = torch.stack([ix, iy, iz], -1).to(self.sdf_abs.dtype)
        return -self.cfg.bound + (ijk + 0.5) * self.cell_size

    def occupied_at(self, x: Tensor) -> Tensor:
        """Occupancy of the cells containing ``x [...,3]`` -> bool ``[...]`` (False outside)."""
        r = self.cfg.resolution
        u = (x / self.cfg.bound + 1.0) * (0.5 * r)
        # cell indices clamped to [-1, r] address a copy of the grid with an empty border cell
        # on every side: one gather, no separate inside test (exact: indices < 2^24 in fp32)
        ijk = torch.floor(u).clamp_(-1.0, float(r)) + 1.0
        p = r + 2
        stride = torch.tensor([p * p, p, 1.0], dtype=ijk.dtype, device=ijk.device)
        flat = (ijk @ stride).long()
        return F.pad(self.occ, (1, 1, 1, 1, 1, 1)).view(-1)[flat]

    def occupied_fraction(self) -> float:
        """Fraction of cells currently occupied."""
        return float(self.occ.float().mean())

    # -- update ---------------------------------------------------------------------
    @torch.no_grad()
    def update(
        self,
        sdf_fn: Callable[[Tensor], Tensor],
        inv_s: float | Tensor,
        step: int | None = None,
        fraction: float = 1.0,
        allowed: Tensor | None = None,
    ) -> dict:
        """Re-evaluate ``|f|`` at cell centres and rebuild ``occ`` with rule (1).

        ``sdf_fn``: ``[M,3] -> [M]`` (called in chunks of ``cfg.chunk``, no grad).
        ``inv_s``: NeuS sharpness ``s`` (float or 0-d tensor). ``fraction < 1``: evaluate a
        random subset of ``ceil(fraction R^3)`` cells (with replacement); the others decay
        (``|f| *= stale_decay``). ``allowed [R,R,R]`` bool (optional, e.g. the masks' visual
        hull): cells outside it are empty and their SDF is not evaluated (the update then costs
        ``allowed.sum()`` SDF queries instead of ``R^3``). ``step`` is informational. Returns
        ``{"occupied_fraction", "threshold", "n_evaluated"}``.
        """
        n_cells = self.sdf_abs.numel()
        dev = self.sdf_abs.device
        keep = None if allowed is None else allowed.reshape(-1).to(dev)
        if fraction >= 1.0 or int(self.n_updates) == 0:
            idx = torch.arange(n_cells, device=dev) if keep is None else keep.nonzero(as_tuple=True)[0]
        else:
            idx = torch.randint(0, n_cells, (max(1, math.ceil(fraction * n_cells)),), device=dev)
            if keep is not None:
                idx = idx[keep[idx]]
            self.sdf_abs.mul_(self.cfg.stale_decay)
        vals = [self.sdf_abs.new_zeros(0)]
        for i in range(0, idx.numel(), self.cfg.chunk):
            c = self.cell_centres(idx[i : i + self.cfg.chunk])
            vals.append(sdf_fn(c).reshape(-1).abs().to(self.sdf_abs.dtype))
        v = torch.cat(vals)
        v = torch.nan_to_num(v, nan=0.0)  # a NaN SDF must never cull
        self.sdf_abs[idx] = v
        thr = self.threshold(float(inv_s))
        r = self.cfg.resolution
        occ = self.sdf_abs <= thr
        if keep is not None:
            occ &= keep
        occ = occ.view(r, r, r)
        if self.cfg.dilation > 0:
            k = 2 * self.cfg.dilation + 1
            occ = F.max_pool3d(occ[None, None].float(), k, stride=1, padding=self.cfg.dilation)[0, 0] > 0
            if keep is not None:
                occ &= keep.view(r, r, r)
        self.occ.copy_(occ)
        self.n_updates += 1
        return {"occupied_fraction": self.occupied_fraction(), "threshold": thr, "n_evaluated": idx.numel()}

    # -- rays -----------------------------------------------------------------------
    def _march(self, rays_o: Tensor, rays_d: Tensor, near: Tensor, far: Tensor, n_march: int | None):
        """Clip ``[near, far]`` to the grid's AABB -> ``[t0, t1]``, split it into ``M`` equal
        segments (``M = n_march`` or ``ceil(2 sqrt(3) bound / delta)``, so each segment is
        ``<= delta`` when ``|d| = 1``; for ``|d| != 1`` pass ``n_march >= 2 sqrt(3) bound |d|_max /
        delta``) and look up the occupancy at their midpoints. Returns ``(edges [B, M+1],
        occupied w [B, M] bool, t0 [B], t1 [B], s [M+1])``."""
        t_in, t_out = ray_aabb(rays_o, rays_d, self.cfg.bound)
        t0 = torch.maximum(near, t_in)
        t1 = torch.minimum(far, t_out)
        valid = t1 > t0
        t1 = torch.where(valid, t1, t0)
        m = n_march or math.ceil(2.0 * math.sqrt(3.0) * self.cfg.bound / self.march_step)
        s = torch.linspace(0.0, 1.0, m + 1, device=rays_o.device, dtype=rays_o.dtype)
        edges = t0[:, None] + (t1 - t0)[:, None] * s  # [B, M+1]
        mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
        pts = rays_o[:, None, :] + rays_d[:, None, :] * mids[..., None]
        w = self.occupied_at(pts) & valid[:, None]  # [B, M]
        return edges, w, t0, t1, s

    @torch.no_grad()
    def ray_hits(self, rays_o: Tensor, rays_d: Tensor, near: Tensor, far: Tensor,
                 n_march: int | None = None) -> Tensor:
        """``[B]`` bool: the ray crosses at least one occupied march segment in ``[near, far]``
        (``rays_o, rays_d [B, 3]``, ``near, far [B]``). By rule (1) a ray that crosses none meets
        no surface: its opacity is ``<= ~e^{-k_s}``."""
        return self._march(rays_o, rays_d, near, far, n_march)[1].any(1)
