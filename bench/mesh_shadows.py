"""Shadow rays against a triangle mesh, in torch (no rtree / embree needed).

The triangles are split into leaves of at most ``leaf`` triangles by recursive median splits of
their centroids along the longest axis; each leaf gets a bounding sphere. A segment
``o + t d, 0 < t < t_max`` is tested against a leaf's triangles (Moller-Trumbore, both faces)
only when it passes within the leaf's sphere, so a shadow ray that leaves the object at once
costs a few sphere tests instead of one test per triangle.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

DET_EPS = 1e-12


def _leaves(centroids: np.ndarray, idx: np.ndarray, leaf: int) -> list[np.ndarray]:
    if len(idx) <= leaf:
        return [idx]
    c = centroids[idx]
    axis = int(np.argmax(c.max(0) - c.min(0)))
    order = idx[np.argsort(c[:, axis], kind="stable")]
    half = len(order) // 2
    return _leaves(centroids, order[:half], leaf) + _leaves(centroids, order[half:], leaf)


def segments_hit_triangles(o: Tensor, d: Tensor, t_max: Tensor, tri: Tensor) -> Tensor:
    """Pairwise any-hit: segments ``o, d [P, 3]`` (d unit), ``t_max [P]`` against their own
    triangle sets ``tri [P, S, 3, 3]`` -> ``[P]`` bool (``0 < t < t_max``, barycentrics in the
    triangle; degenerate triangles never hit)."""
    v0, e1, e2 = tri[:, :, 0], tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0]
    dd = d[:, None].expand_as(e2)
    p = torch.cross(dd, e2, dim=-1)
    det = (e1 * p).sum(-1)
    ok = det.abs() >= DET_EPS
    inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
    s = o[:, None] - v0
    u = (s * p).sum(-1) * inv
    q = torch.cross(s, e1, dim=-1)
    w = (dd * q).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    return (ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0) & (t < t_max[:, None])).any(-1)


class MeshShadows:
    """Any-hit queries against a fixed mesh (``vertices [V, 3]``, ``faces [F, 3]``, one frame)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, leaf: int = 64) -> None:
        tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
        groups = _leaves(tri.mean(1), np.arange(len(tri)), leaf)
        S = max(len(g) for g in groups)
        packed = np.zeros((len(groups), S, 3, 3))  # padding: degenerate (all-zero) triangles
        centre = np.zeros((len(groups), 3))
        radius = np.zeros(len(groups))
        for k, g in enumerate(groups):
            packed[k, :len(g)] = tri[g]
            pts = tri[g].reshape(-1, 3)
            centre[k] = 0.5 * (pts.min(0) + pts.max(0))
            radius[k] = np.linalg.norm(pts - centre[k], axis=-1).max()
        self.tri = torch.from_numpy(packed)
        self.centre = torch.from_numpy(centre)
        self.radius = torch.from_numpy(radius) * (1 + 1e-9) + 1e-12

    def any_hit(self, o: Tensor, d: Tensor, t_max: Tensor, chunk: int = 4096, pair_chunk: int = 4096) -> Tensor:
        """``[N]`` bool: the segment ``o + t d`` (``d`` unit), ``0 < t < t_max``, crosses a triangle."""
        o, d, t_max = o.double().cpu(), d.double().cpu(), t_max.double().cpu()
        out = torch.zeros(o.shape[0], dtype=torch.bool)
        for a in range(0, o.shape[0], chunk):
            oc, dc, tc = o[a:a + chunk], d[a:a + chunk], t_max[a:a + chunk]
            rel = self.centre[None] - oc[:, None]                                     # [R, C, 3]
            t = (rel * dc[:, None]).sum(-1).clamp_min(0.0).minimum(tc[:, None])    # closest approach
            gap = rel - t[..., None] * dc[:, None]
            ray_i, leaf_i = ((gap * gap).sum(-1) <= self.radius[None] ** 2).nonzero(as_tuple=True)
            hit = torch.zeros(oc.shape[0], dtype=torch.bool)
            for b in range(0, ray_i.shape[0], pair_chunk):
                r, lf = ray_i[b:b + pair_chunk], leaf_i[b:b + pair_chunk]
                h = segments_hit_triangles(oc[r], dc[r], tc[r], self.tri[lf])
                hit[r[h]] = True
            out[a:a + chunk] = hit
        return out

    def visibility(self, offset: float):
        """A :data:`nepf_core.relight.shade.VisibilityFn`: 1 where the segment from ``x + offset n``
        to the light crosses no triangle, else 0."""
        def vis(x: Tensor, n: Tensor, p: Tensor) -> Tensor:
            o = (x + offset * n).double().cpu()
            to_light = p.double().cpu()[None, :] - o
            dist = to_light.norm(dim=-1)
            blocked = self.any_hit(o, to_light / dist.clamp_min(1e-12)[:, None], dist)
            return (~blocked).to(x.dtype).to(x.device)
        return vis
