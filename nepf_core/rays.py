"""Rays from a :class:`Scene`: typed batches and a pixel sampler living on the device.

A pixel (column i, row j) of view k gives (pinhole; pixel centres at +0.5, see Scene)

    d_cam = K_k^{-1} [i + 0.5, j + 0.5, 1]^T,   d = normalize(R_k d_cam),   o = t_k

where ``[R_k | t_k]`` is the top of ``c2w_k`` (normalised frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nepf_core.data.scene import Scene


@dataclass
class RayBatch:
    """A batch of rays with their supervision.

    Attributes:
        origins: ``[R, 3]``; directions: ``[R, 3]`` unit; rgb: ``[R, 3]`` linear ground truth
        (or None at inference); mask: ``[R]`` float 0/1 or None; view: ``[R]`` long view index.
    """

    origins: Tensor
    directions: Tensor
    rgb: Tensor | None = None
    mask: Tensor | None = None
    view: Tensor | None = None
    unlit: Tensor | None = None
    """``[R]`` bool, training only: the target pixel is unlit (see ``unlit_threshold``)."""
    weight: Tensor | None = None
    """``[R]`` float, training only: importance weight of the ray in per-ray means of the
    mask loss (``1 / p_keep`` after :mod:`nepf_core.train.rules.empty_rays`; None: all 1)."""

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def slice(self, a: int, b: int) -> "RayBatch":
        return RayBatch(self.origins[a:b], self.directions[a:b],
                        None if self.rgb is None else self.rgb[a:b],
                        None if self.mask is None else self.mask[a:b],
                        None if self.view is None else self.view[a:b],
                        None if self.unlit is None else self.unlit[a:b],
                        None if self.weight is None else self.weight[a:b])

    def index(self, idx: Tensor) -> "RayBatch":
        return RayBatch(self.origins[idx], self.directions[idx],
                        None if self.rgb is None else self.rgb[idx],
                        None if self.mask is None else self.mask[idx],
                        None if self.view is None else self.view[idx],
                        None if self.unlit is None else self.unlit[idx],
                        None if self.weight is None else self.weight[idx])


def foreground_peaks(images: np.ndarray, masks: np.ndarray | None) -> np.ndarray:
    """``max_c I`` of every foreground pixel (every pixel without masks): ``[N, H, W, 3] -> [P]``."""
    peak = images.max(-1)
    return peak[masks > 0.5] if masks is not None else peak.reshape(-1)


def unlit_threshold(images: np.ndarray, masks: np.ndarray | None, rel: float) -> float:
    """Linear value under which a pixel counts as unlit: ``rel * q99(max_c I)`` over the
    foreground (every pixel without masks). Relative, so a uniformly dark capture (8-bit
    values < 8) still has lit pixels. ``images [N, H, W, 3]`` linear, ``masks [N, H, W]``."""
    vals = foreground_peaks(images, masks)
    if vals.size == 0:
        return 0.0
    step = max(1, vals.size // 2_000_000)  # a subsample is plenty for a quantile
    return float(rel * np.quantile(vals[::step], 0.99))


def rays_from_pixels(K_inv: Tensor, c2w: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """World rays through pixel coordinates.

    Args: ``K_inv [R,3,3]``, ``c2w [R,4,4]``, ``u, v [R]`` (float pixel coordinates).
    Returns: ``origins [R,3]``, unit ``directions [R,3]``.
    """
    p = torch.stack([u, v, torch.ones_like(u)], dim=-1)
    d_cam = torch.einsum("rij,rj->ri", K_inv, p)
    d = torch.einsum("rij,rj->ri", c2w[:, :3, :3], d_cam)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return c2w[:, :3, 3].clone(), d


class PixelSampler:
    """Holds a scene's images and cameras on a device and draws random ray batches.

    Images are kept as float16 to halve memory (8-bit sources lose nothing).
    """

    def __init__(self, scene: Scene, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self.n_views, self.height, self.width = scene.n_views, scene.height, scene.width
        self.images = torch.from_numpy(np.ascontiguousarray(scene.images)).to(self.device, torch.float16)
        self.masks = None if scene.masks is None else torch.from_numpy(scene.masks).to(self.device)
        K = torch.from_numpy(scene.intrinsics.astype(np.float64))
        self.K_inv = torch.linalg.inv(K).to(self.device, torch.float32)
        self.c2w = torch.from_numpy(scene.c2w.astype(np.float32)).to(self.device)

    def _gather(self, view: Tensor, row: Tensor, col: Tensor, at: tuple[float, float] = (0.5, 0.5)) -> RayBatch:
        """The rays through ``(col + at[0], row + at[1])`` (``at``: the point within the pixel,
        ``(0.5, 0.5)`` its centre) with the pixels' colour and mask."""
        o, d = rays_from_pixels(self.K_inv[view], self.c2w[view], col.float() + at[0], row.float() + at[1])
        rgb = self.images[view, row, col].float()
        mask = None if self.masks is None else self.masks[view, row, col].float()
        return RayBatch(o, d, rgb, mask, view)

    def sample(self, n: int, generator: torch.Generator | None = None,
               views: Tensor | None = None) -> RayBatch:
        """``n`` rays at uniformly random pixels (of ``views`` when given)."""
        g = generator
        dev = self.device
        if views is None:
            view = torch.randint(0, self.n_views, (n,), generator=g, device="cpu")
        else:
            view = views[torch.randint(0, len(views), (n,), generator=g, device="cpu")]
        row = torch.randint(0, self.height, (n,), generator=g, device="cpu")
        col = torch.randint(0, self.width, (n,), generator=g, device="cpu")
        return self._gather(view.to(dev), row.to(dev), col.to(dev))

    def pixel_rays(self, view: Tensor, row: Tensor, col: Tensor, at: tuple[float, float] = (0.5, 0.5)) -> RayBatch:
        """The rays of the pixels ``(view, row, col)`` ``[R]`` long, each through the point ``at``
        (x, y in [0, 1)) of its pixel: the centre by default."""
        return self._gather(view, row, col, at)

    def view_rays(self, k: int, stride: int = 1) -> RayBatch:
        """All pixels of view ``k`` (every ``stride``-th row/column), row-major."""
        rows = torch.arange(0, self.height, stride, device=self.device)
        cols = torch.arange(0, self.width, stride, device=self.device)
        rr, cc = torch.meshgrid(rows, cols, indexing="ij")
        view = torch.full_like(rr.reshape(-1), k)
        return self._gather(view, rr.reshape(-1), cc.reshape(-1))
