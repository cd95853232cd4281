"""The free-space prior of captures without masks: what the cameras see through is empty.

Without masks nothing tells the SDF early that the space in front of the wall is empty. The
photometric loss alone lets it paint the wall and the object onto the front of the region (the
SDF negative in the whole region, a painted ball), and the background volume behind never gets
the gradient that would let it take the wall over: a local minimum that a CPU budget of a few
thousand steps does not leave (bench/RESULTS.md v23).

The images say more: a point ``p`` triangulated from views ``i`` and ``j``
(:mod:`nepf_core.data.sparse_points`) is seen by both, so the segments from their camera centres
``o`` to ``p`` are empty. On each training step ``n_samples`` such segments are drawn, clipped to
the part of the ray the SDF models (:func:`nepf_core.render.sampling.object_segment`) and ended
``margin`` before ``p`` (the point's own error), and one point ``x`` uniform on each gets

    L_free = mean_x relu(tau - f(x))

which is zero wherever the SDF already says "outside by at least tau" and pushes it there
elsewhere. It never asks for a surface (only for empty space), so a point mis-triangulated in
front of the true surface costs nothing; one behind it carves a thin line, which the
photometric loss of the many rays that see the surface outweighs. Shapes: points ``[P, 3]``,
origins ``[P, 3]`` (each point once per view that saw it), normalised frame.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from nepf_core.render.sampling import object_segment


class FreeSpacePrior:
    """Samples on camera-to-point segments and their hinge loss (module docstring)."""

    def __init__(self, sparse, c2w: np.ndarray, halfspace, device, *, n_samples: int = 1024,
                 margin: float = 0.1, tau: float = 0.02) -> None:
        centres = np.asarray(c2w)[:, :3, 3]
        pts = np.asarray(sparse.points)
        views = np.asarray(sparse.views)
        self.points = torch.as_tensor(np.concatenate([pts, pts]), dtype=torch.float32, device=device)
        self.origins = torch.as_tensor(np.concatenate([centres[views[:, 0]], centres[views[:, 1]]]),
                                       dtype=torch.float32, device=device)
        self.halfspace = halfspace
        self.n_samples, self.margin, self.tau = n_samples, margin, tau

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def sample(self, generator: torch.Generator | None = None) -> Tensor:
        """Points on empty segments inside the SDF's region: ``[<= n_samples, 3]``."""
        dev = self.points.device
        idx = torch.randint(0, len(self), (self.n_samples,), generator=generator).to(dev)
        o, p = self.origins[idx], self.points[idx]
        v = p - o
        length = v.norm(dim=-1).clamp_min(1e-9)
        d = v / length[:, None]
        near, far, hit, _ = object_segment(o, d, self.halfspace)
        end = torch.minimum(far, length - self.margin)
        ok = hit & (end > near)
        u = torch.rand(self.n_samples, generator=generator).to(dev)
        t = near + u * (end - near)
        return (o + t[:, None] * d)[ok]

    def loss(self, model, generator: torch.Generator | None = None) -> Tensor:
        """``mean relu(tau - f(x))`` over :meth:`sample` (0 when no segment crosses the region)."""
        x = self.sample(generator)
        if x.shape[0] == 0:
            return self.points.new_zeros(())
        return torch.relu(self.tau - model.sdf.sdf(x).reshape(-1)).mean()
