"""The sparse-point prior of captures without masks: triangulated points lie on a surface.

Without masks nothing but the photometric loss shapes the SDF, and on a CPU budget of a few
thousand steps that is not enough: on the fox the zero level set stayed the initial sphere
(r = 0.5) and the head was painted onto it, fur and snout left as a fog around it
(bench/RESULTS.md v23). The images say more: the points triangulated from them before training
(:mod:`nepf_core.data.sparse_points`, the ones in the object region,
:func:`nepf_core.train.rules.masks.decide_object_region`) are where the cameras saw a surface.
As in Geo-NeuS (Fu et al. 2022, "explicit SDF supervision on sparse points"), each step draws
``n_samples`` of them and asks the SDF to vanish there:

    L_points = mean_p |f(p)|,   p in the object region's points   [P, 3] -> []

L1, so a mismatched point costs at most a constant pull (its gradient is bounded), which the
photometric loss of the many rays through it outweighs. Not in the paper (its scenes have masks).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


class SurfacePointPrior:
    """``mean |f(p)|`` over a random draw of the triangulated object points (module docstring)."""

    def __init__(self, points: np.ndarray, device, n_samples: int = 512) -> None:
        self.points = torch.as_tensor(np.asarray(points), dtype=torch.float32, device=device).reshape(-1, 3)
        self.n_samples = n_samples

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def loss(self, model, generator: torch.Generator | None = None) -> Tensor:
        """``mean_p |f(p)|`` over ``min(n_samples, P)`` points drawn with replacement (0 without points)."""
        if len(self) == 0:
            return self.points.new_zeros(())
        idx = torch.randint(0, len(self), (min(self.n_samples, len(self)),), generator=generator)
        return model.sdf.sdf(self.points[idx.to(self.points.device)]).reshape(-1).abs().mean()
