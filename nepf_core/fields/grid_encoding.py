"""Multi-resolution dense grid encoding (the `fast` preset's SDF input) and a sphere prior.

Why dense grids and not a hash grid: on the 2-core CPU target a pure-torch hash grid
costs several times more per forward+backward than a trilinear lookup in a few dense volumes
(docs/FAST.md).

Conventions
-----------
* Input ``x`` lives in ``[-bound, bound]^3`` (normalised frame), shape ``[N, 3]``.
  Points outside are clamped to the border (``padding_mode="border"``).
* The levels live in one parameter ``table [sum_l R_l^3, F]``, level ``l`` in rows
  ``first_row_l .. first_row_l + R_l^3 - 1``, one row per node, node ``(i, j, k)`` along
  ``(x, y, z)`` at row ``first_row_l + (k R_l + j) R_l + i`` (the ``grid_sample`` volume
  ``[1, F, R_l, R_l, R_l]``, ``[z, y, x]``-indexed, transposed); :meth:`MultiResGrid.level`
  gives level ``l``'s rows. The ``R_l`` nodes per axis sit
  on ``-bound + 2*bound*i/(R_l-1)`` (``align_corners=True``), so the cell size is
  ``h_l = 2*bound/(R_l-1)``. The lookup is :func:`nepf_core.fields.trilinear.trilinear_lookup`:
  one lookup for all active levels, whose backward touches only the rows a step read (why:
  that module's docstring).
* Resolutions grow geometrically:
  ``R_l = round(base * b**l)``, ``b = (max_resolution/base) ** (1/(n_levels-1))``.
* Output ``[N, n_levels*F]``, level-major (``[l0f0..l0fF-1, l1f0, ...]``).
  Levels ``>= active_levels`` output exact zeros and receive no gradient
  (coarse-to-fine, Neuralangelo-style).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from nepf_core.fields.trilinear import LevelLayout, trilinear_lookup

__all__ = ["GridConfig", "MultiResGrid", "sphere_sdf"]


@dataclass
class GridConfig:
    """Configuration of :class:`MultiResGrid`."""

    n_levels: int = 4
    """Number of dense levels."""
    base_resolution: int = 16
    """Nodes per axis of the coarsest level."""
    max_resolution: int = 128
    """Nodes per axis of the finest level."""
    features_per_level: int = 4
    """Feature channels per level (F)."""
    init_std: float = 1e-4
    """Std of the normal init of the grid values (small: the sphere prior dominates at start)."""
    bound: float = 1.0
    """Half extent of the encoded cube ``[-bound, bound]^3``."""
    start_levels: int = 1
    """Levels active at progress 0 (see :meth:`MultiResGrid.set_progress`)."""

    def resolutions(self) -> list[int]:
        """Per-level resolutions ``R_l = round(base * b**l)`` (nodes per axis)."""
        if self.n_levels == 1:
            return [int(self.max_resolution)]
        b = (self.max_resolution / self.base_resolution) ** (1.0 / (self.n_levels - 1))
        return [int(round(self.base_resolution * b**level)) for level in range(self.n_levels)]


class MultiResGrid(nn.Module):
    """Multi-resolution dense feature grid, trilinear lookup (:func:`trilinear_lookup`).

    ``forward(x [N,3]) -> [N, n_levels*F]`` with
    ``out[:, l*F:(l+1)*F] = trilinear(V_l, x / bound)`` for active levels ``l`` and zeros
    otherwise. Differentiable w.r.t. ``x`` and the grids. Double backward (eikonal via
    ``create_graph=True``) works in torch 2.13 but costs ~7.6x the 4-point finite-difference
    normals on CPU (docs/FAST.md), so the fast SDF uses :mod:`nepf_core.fields.fd_normals`.
    """

    def __init__(self, cfg: GridConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or GridConfig()
        self.resolutions = cfg.resolutions()
        f = cfg.features_per_level
        # each level drawn in the volume layout [1, F, R, R, R], stored as rows [R^3, F]
        self.table = nn.Parameter(torch.cat([(torch.randn(1, f, r, r, r) * cfg.init_std).reshape(f, -1).t()
                                             for r in self.resolutions]).contiguous())
        sizes = [r ** 3 for r in self.resolutions]
        self.first_rows = [sum(sizes[:level]) for level in range(len(sizes))]
        self.layout = LevelLayout(self.resolutions, self.first_rows)
        self.active_levels = cfg.n_levels
        self.set_active_levels(max(1, min(cfg.start_levels, cfg.n_levels)))

    # -- coarse-to-fine -------------------------------------------------------------
    @property
    def n_output_dims(self) -> int:
        """``n_levels * features_per_level``."""
        return self.cfg.n_levels * self.cfg.features_per_level

    def set_active_levels(self, k: int) -> None:
        """Activate levels ``0..k-1`` (clamped to ``[1, n_levels]``); finer ones output 0."""
        self.active_levels = int(max(1, min(int(k), self.cfg.n_levels)))

    def set_progress(self, p: float) -> int:
        """Linear coarse-to-fine schedule on progress ``p`` in ``[0, 1]``.

        ``k = start + floor(p * (n_levels - start + 1))`` clamped to ``n_levels``, so all
        levels are active for the last ``1/(n_levels-start+1)`` of the schedule.
        Returns the number of active levels.
        """
        s = max(1, min(self.cfg.start_levels, self.cfg.n_levels))
        p = min(max(float(p), 0.0), 1.0)
        self.set_active_levels(s + int(math.floor(p * (self.cfg.n_levels - s + 1))))
        return self.active_levels

    def cell_size(self, level: int) -> float:
        """Cell size ``h_l = 2*bound/(R_l-1)`` of level ``level``."""
        return 2.0 * self.cfg.bound / (self.resolutions[level] - 1)

    def active_cell_size(self) -> float:
        """Cell size of the finest active level (use it to set the FD normal step)."""
        return self.cell_size(self.active_levels - 1)

    # checkpointing of the schedule state (restored by load_state_dict)
    def get_extra_state(self):
        return {"active_levels": self.active_levels}

    def set_extra_state(self, state) -> None:
        self.set_active_levels(int(state["active_levels"]))

    def level(self, level: int) -> Tensor:
        """Level ``level``'s rows of the table, ``[R_l^3, F]`` (a view)."""
        r = self.resolutions[level]
        return self.table[self.first_rows[level]:self.first_rows[level] + r ** 3]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """Checkpoints that stored one ``grid_sample`` volume per level (``grids.<l>``,
        ``[1, F, R, R, R]``) load into the table."""
        old = [state_dict.pop(f"{prefix}grids.{level}") for level in range(len(self.resolutions))
               if f"{prefix}grids.{level}" in state_dict]
        if old:
            state_dict[f"{prefix}table"] = torch.cat([v.reshape(v.shape[1], -1).t() for v in old]).contiguous()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # -- lookup ---------------------------------------------------------------------
    def forward(self, x: Tensor) -> Tensor:
        """Encode ``x [N,3]`` -> ``[N, n_levels*F]`` (dtype of the grids)."""
        k = self.active_levels
        feats = trilinear_lookup(self.table, x, self.layout, k, self.cfg.bound)
        feats = feats.reshape(x.shape[0], -1)                                  # [N, k*F], level-major
        n_off = self.cfg.n_levels - k
        if n_off:
            feats = torch.cat([feats, feats.new_zeros(x.shape[0], n_off * self.cfg.features_per_level)], 1)
        return feats


def sphere_sdf(x: Tensor, radius: float | Tensor = 0.5) -> Tensor:
    """Analytic sphere SDF ``f(x) = |x| - radius``; ``x [..., 3] -> [...]``.

    Use it as a prior: ``sdf(x) = sphere_sdf(x, r) + residual(x)`` with the residual's
    last layer initialised at (near) zero, so training starts from a sphere of radius
    ``r`` with ``|grad f| = 1`` everywhere (eikonal-exact) and the normals pointing out.
    """
    return torch.linalg.vector_norm(x, dim=-1) - radius
