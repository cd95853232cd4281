"""Paper SDF network: positional encoding + 8x256 MLP with a skip, geometric init.

    (sdf, feature) = MLP(PE_L(x)),   x in the normalised frame, ``[N, 3] -> [N], [N, F]``

The supplementary says "ReLU"; we use softplus(beta=100), NeuS's smooth ReLU, because a
ReLU SDF has a zero Hessian almost everywhere, which would make the paper's Hessian loss
vacuous. ``activation="relu"`` is available for the strict variant.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from nepf_core.mlp import MLPConfig, build_mlp, encoding_dim, positional_encoding


@dataclass
class MLPSDFConfig:
    """SDF MLP settings (defaults: the paper / NeuS)."""

    width: int = 256
    """Hidden width."""
    depth: int = 8
    """Hidden layers."""
    feature_dim: int = 256
    """Size of the feature vector passed to the other networks."""
    n_freqs: int = 6
    """Positional-encoding frequencies for x (NeuS: 6)."""
    activation: str = "softplus"
    """softplus (default, see module doc) or relu."""
    init_radius: float = 0.5
    """Geometric-init sphere radius (NeuS: 0.5)."""
    skips: tuple[int, ...] = (4,)
    """Skip connection layers."""
    weight_norm: bool = True
    """Weight normalisation as in NeuS."""


class MLPSDF(nn.Module):
    """The paper's SDF network. ``forward(x [N,3]) -> (sdf [N], feature [N, F])``."""

    uses_fd_normals = False

    def __init__(self, cfg: MLPSDFConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.feature_dim = cfg.feature_dim
        self.mlp = build_mlp(MLPConfig(
            in_dim=encoding_dim(3, cfg.n_freqs), out_dim=1 + cfg.feature_dim, width=cfg.width,
            depth=cfg.depth, activation=cfg.activation, skips=cfg.skips, geometric_init=True,
            init_radius=cfg.init_radius, n_raw_inputs=3, weight_norm=cfg.weight_norm))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        out = self.mlp(positional_encoding(x, self.cfg.n_freqs))
        return out[..., 0], out[..., 1:]

    def sdf(self, x: Tensor) -> Tensor:
        """SDF only: ``[N, 3] -> [N]``."""
        return self.forward(x)[0]

    def set_progress(self, progress: float) -> None:
        """No coarse-to-fine schedule for the MLP."""

    def fd_step(self) -> float:
        """Finite-difference step for the Hessian regulariser (normalised units)."""
        return 1e-3
