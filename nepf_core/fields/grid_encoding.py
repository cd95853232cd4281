"""Multi-resolution dense grid encoding (the `fast` preset's SDF input) and a sphere prior.

Why dense grids and not a hash grid: on the 2-core CPU target a pure-torch hash grid
costs several times more per forward+backward than ``F.grid_sample`` on a few dense volumes
(docs/FAST.md).

Conventions
-----------
* Input ``x`` lives in ``[-bound, bound]^3`` (normalised frame), shape ``[N, 3]``.
  Points outside are clamped to the border (``padding_mode="border"``).
* Level ``l`` is a parameter of shape ``[1, F, R_l, R_l, R_l]`` (grid_sample layout
  ``[B, C, D, H, W]``, i.e. indexed ``[z, y, x]``). With ``align_corners=True`` the
  ``R_l`` nodes sit on ``-bound + 2*bound*i/(R_l-1)``, so the cell size is
  ``h_l = 2*bound/(R_l-1)``.
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
import torch.nn.functional as F
from torch import Tensor, nn

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
    """Multi-resolution dense feature grid, trilinear lookup with ``F.grid_sample``.

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
        self.grids = nn.ParameterList(
            [
                nn.Parameter(torch.randn(1, cfg.features_per_level, r, r, r) * cfg.init_std)
                for r in self.resolutions
            ]
        )
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

    # -- lookup ---------------------------------------------------------------------
    def forward(self, x: Tensor) -> Tensor:
        """Encode ``x [N,3]`` -> ``[N, n_levels*F]`` (dtype of the grids)."""
        n = x.shape[0]
        g = (x / self.cfg.bound).to(self.grids[0].dtype).view(1, n, 1, 1, 3)
        feats = []
        for level in range(self.active_levels):
            v = F.grid_sample(
                self.grids[level], g, mode="bilinear", padding_mode="border", align_corners=True
            )  # [1, F, N, 1, 1]
            feats.append(v.view(-1, n))
        n_off = self.cfg.n_levels - self.active_levels
        if n_off:
            feats.append(g.new_zeros(n_off * self.cfg.features_per_level, n))
        return torch.cat(feats, 0).t()


def sphere_sdf(x: Tensor, radius: float | Tensor = 0.5) -> Tensor:
    """Analytic sphere SDF ``f(x) = |x| - radius``; ``x [..., 3] -> [...]``.

    Use it as a prior: ``sdf(x) = sphere_sdf(x, r) + residual(x)`` with the residual's
    last layer initialised at (near) zero, so training starts from a sphere of radius
    ``r`` with ``|grad f| = 1`` everywhere (eikonal-exact) and the normals pointing out.
    """
    return torch.linalg.vector_norm(x, dim=-1) - radius
