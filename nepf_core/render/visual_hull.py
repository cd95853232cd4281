"""Visual hull from foreground masks: which occupancy cells can hold the object at all.

A cell of centre c (half-diagonal r_h) is kept iff, in every view where it projects
inside the image, its projection lands on a mask pixel after dilating the mask by the
cell's projected radius ``ceil(f r_h / z_min) + 1`` pixels (z_min: nearest depth of the
cell). Dilation makes the test conservative: a cell that contains any foreground point of
a view is never culled, so the hull only removes space no mask allows.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F


def visual_hull_cells(scene, resolution: int, bound: float = 1.0, device="cpu") -> torch.Tensor:
    """``[R, R, R]`` bool (indexed [x, y, z] like the occupancy grid's cell order) of kept cells."""
    R = resolution
    h = 2.0 * bound / R
    r_h = math.sqrt(3.0) * 0.5 * h
    ax = (torch.arange(R, dtype=torch.float64) + 0.5) * h - bound
    X, Y, Z = torch.meshgrid(ax, ax, ax, indexing="ij")
    pts = torch.stack([X, Y, Z], -1).reshape(-1, 3)
    keep = torch.ones(pts.shape[0], dtype=torch.bool)
    masks = torch.from_numpy(scene.masks)
    H, W = scene.height, scene.width
    for k in range(scene.n_views):
        c2w = torch.from_numpy(scene.c2w[k].astype(np.float64))
        w2c = torch.linalg.inv(c2w)
        K = torch.from_numpy(scene.intrinsics[k].astype(np.float64))
        pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        front = z > 1e-6
        uv = (pc @ K.T)[:, :2] / z.clamp_min(1e-6)[:, None]
        u = torch.floor(uv[:, 0]).long()  # pixel centres at +0.5 (Scene convention)
        v = torch.floor(uv[:, 1]).long()
        inimg = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        zmin = max(float(z[front].min()) - r_h, 1e-3) if front.any() else 1.0
        rad = int(math.ceil(float(K[0, 0]) * r_h / zmin)) + 1
        m = masks[k].float()[None, None]
        md = F.max_pool2d(m, 2 * rad + 1, stride=1, padding=rad)[0, 0] > 0.5
        ok = torch.ones_like(keep)
        idx = inimg.nonzero(as_tuple=True)[0]
        ok[idx] = md[v[idx], u[idx]]
        keep &= ok
    # the occupancy grid indexes cells as flat (ix * R + iy) * R + iz? match its convention
    return keep.reshape(R, R, R).to(device)
