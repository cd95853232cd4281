"""A small random multi-resolution grid and its levels as ``grid_sample`` volumes: the reference
the trilinear lookup's tests compare against (test_trilinear_lookup.py, test_exact_sdf_gradient.py)."""
from __future__ import annotations

import torch

from nepf_core.fields.grid_encoding import GridConfig, MultiResGrid


def random_grid(levels: int = 3, feats: int = 3, bound: float = 1.0, seed: int = 0) -> MultiResGrid:
    """Levels 4..11 nodes per axis, unit-variance values, float64, every level active."""
    torch.manual_seed(seed)
    g = MultiResGrid(GridConfig(n_levels=levels, base_resolution=4, max_resolution=11, features_per_level=feats,
                                init_std=1.0, bound=bound)).double()
    g.set_active_levels(levels)
    return g


def level_volumes(g: MultiResGrid) -> list[torch.Tensor]:
    """Each level as the ``grid_sample`` volume ``[1, F, R, R, R]`` (a leaf of its own)."""
    f = g.cfg.features_per_level
    return [g.level(l).detach().t().reshape(1, f, r, r, r).clone().requires_grad_()
            for l, r in enumerate(g.resolutions)]
