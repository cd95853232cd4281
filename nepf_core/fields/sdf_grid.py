"""Fast SDF: multi-resolution dense grid + a small MLP head on a sphere prior.

    h = MLP([G(x), x]),   sdf(x) = |x| - r + h_0,   feature(x) = h_{1:}

``G`` is :class:`nepf_core.fields.grid_encoding.MultiResGrid` (trilinear, :mod:`nepf_core.fields.trilinear`),
activated coarse-to-fine through :meth:`set_progress`. The SDF row of the head's last
layer starts at zero, so training starts from a sphere of radius ``r`` with exact unit
gradient. The lookup's table gradient is scattered outside autograd (no double backward), so this
field is used with central-difference normals whose step follows the finest active cell.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from nepf_core.fields.grid_encoding import GridConfig, MultiResGrid, sphere_sdf
from nepf_core.mlp import MLPConfig, build_mlp


@dataclass
class GridSDFConfig:
    """Grid SDF settings (the ``fast`` preset)."""

    n_levels: int = 4
    """Dense levels."""
    base_resolution: int = 16
    """Coarsest grid nodes per axis."""
    max_resolution: int = 128
    """Finest grid nodes per axis."""
    features_per_level: int = 2
    """Channels per level (2: the lookup and its gradient scatter scale with it;
    it dominated a fast step's CPU time at 4)."""
    start_levels: int = 2
    """Levels active at the start of the coarse-to-fine schedule."""
    width: int = 64
    """Head width."""
    depth: int = 1
    """Head hidden layers."""
    feature_dim: int = 16
    """Feature vector passed to the radiance / photon / material networks."""
    init_radius: float = 0.5
    """Sphere prior radius."""
    fd_step_cells: float = 0.5
    """Finite-difference step in units of the finest active cell size."""


class GridSDF(nn.Module):
    """``forward(x [N,3]) -> (sdf [N], feature [N, F])``."""

    uses_fd_normals = True

    def __init__(self, cfg: GridSDFConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.feature_dim = cfg.feature_dim
        self.encoding = MultiResGrid(GridConfig(n_levels=cfg.n_levels, base_resolution=cfg.base_resolution,
                                                max_resolution=cfg.max_resolution,
                                                features_per_level=cfg.features_per_level,
                                                start_levels=cfg.start_levels))
        self.head = build_mlp(MLPConfig(in_dim=self.encoding.n_output_dims + 3, out_dim=1 + cfg.feature_dim,
                                        width=cfg.width, depth=cfg.depth, activation="relu"))
        last = self.head.layers[-1]
        with torch.no_grad():
            last.weight[0].zero_()
            last.bias[0] = 0.0

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        h = self.head(torch.cat([self.encoding(x), x], dim=-1))
        return sphere_sdf(x, self.cfg.init_radius) + h[:, 0], h[:, 1:]

    def sdf(self, x: Tensor) -> Tensor:
        """SDF only: ``[N, 3] -> [N]``."""
        return self.forward(x)[0]

    def set_progress(self, progress: float) -> None:
        """Coarse-to-fine: activate grid levels with training progress in [0, 1]."""
        self.encoding.set_progress(progress)

    def fd_step(self) -> float:
        """Central-difference step: ``fd_step_cells`` x the finest active cell size."""
        return self.cfg.fd_step_cells * self.encoding.active_cell_size()
