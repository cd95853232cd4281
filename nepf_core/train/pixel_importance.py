"""Where to draw the training rays: part uniform, part where the radiance network still fits worst.

A uniform pixel draw spends the batch in proportion to area. A highlight covers ~1 % of a
glossy object's pixels, so a 1,024-ray batch holds about ten of them; the radiance network
learns them late and at about half their intensity (bench/RESULTS.md v48, part 3), and the PBR
branch, which ``L_surf`` teaches from that network, never makes a highlight, so its roughness
has nothing to fit. Instant-NGP draws part of each batch from an error map for the same reason.

The pixels of all views are grouped into ``C`` tiles (``t x t`` pixel squares of one view, ``t``
chosen so that ``C <= max_cells``). Each tile keeps ``e_c``, the last display-space error of a
ray drawn in it, blended ``e_c <- (1 - b) e_c + b e`` (``b`` = :data:`BLEND`), where a ray's error
is

    e = mean_c |srgb(L_r) - srgb(L_gt)| [foreground]  +  |sum_i w_i - mask|   (the mask term with masks)

A batch of ``n`` rays is ``n - k`` uniform pixels and ``k = round(fraction n)`` pixels drawn from
tiles with probability ``p_c = e_c / sum e`` (inverse CDF of one uniform number per ray, so a
CPU generator drives it on any device without a host sync), uniform within the tile. Every tile
starts at :data:`START_ERROR`, above any error a ray shows, so a tile that was never drawn is
preferred to one that is known to fit.

The losses are not re-weighted by ``1 / p``: the point is to weigh the pixels the network misses
more, as a larger share of the batch, not to estimate the uniform mean with less variance.

Cost: one cumulative sum over ``C`` floats, a ``searchsorted`` of ``k`` rays and a scatter of
``n`` errors a step (``C = 32768``: well under a millisecond on a CPU).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from nepf_core.color import linear_to_srgb

MAX_CELLS = 32768
"""``C`` at most: with 1,024 rays a step every tile is drawn ~30 times in 1,000 steps."""
BLEND = 0.5
"""``b``: a tile's error follows its last draws (a highlight that the network has learnt stops
being drawn within a few visits)."""
START_ERROR = 1.0
"""``e_c`` before a tile's first draw (display-space errors are at most 1 per term)."""


class PixelImportance:
    """The tile errors of the module docstring for ``n_views`` images of ``height x width``."""

    def __init__(self, n_views: int, height: int, width: int, device: torch.device | str,
                 fraction: float, max_cells: int = MAX_CELLS) -> None:
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"PixelImportance: fraction must lie in [0, 1], got {fraction}")
        if min(n_views, height, width) < 1 or max_cells < 1:
            raise ValueError("PixelImportance: needs at least one view, one pixel and one cell")
        self.fraction = float(fraction)
        self.n_views, self.height, self.width = n_views, height, width
        self.tile = max(1, math.ceil(math.sqrt(n_views * height * width / max_cells)))
        self.rows, self.cols = math.ceil(height / self.tile), math.ceil(width / self.tile)
        self.error = torch.full((n_views * self.rows * self.cols,), START_ERROR, device=device)

    def cells(self, view: Tensor, row: Tensor, col: Tensor) -> Tensor:
        """``[R]`` long: the tile of each pixel (``view, row, col [R]`` long)."""
        return (view * self.rows + row // self.tile) * self.cols + col // self.tile

    def draw(self, n: int, generator: torch.Generator | None) -> tuple[Tensor, Tensor, Tensor]:
        """``(view, row, col)`` ``[n]`` long each, on the map's device: ``n - k`` uniform pixels,
        then ``k`` drawn from the tiles by their error (module docstring)."""
        dev = self.error.device
        k = int(round(self.fraction * n))
        view = torch.randint(0, self.n_views, (n,), generator=generator).to(dev)
        row = torch.randint(0, self.height, (n,), generator=generator).to(dev)
        col = torch.randint(0, self.width, (n,), generator=generator).to(dev)
        if k == 0:
            return view, row, col
        u = torch.rand(k, generator=generator).to(dev)
        cdf = torch.cumsum(self.error, 0)
        cell = torch.searchsorted(cdf, u * cdf[-1], right=True).clamp_max(self.error.numel() - 1)
        per_view = self.rows * self.cols
        v, rest = cell // per_view, cell % per_view
        # a uniform pixel inside the tile (the last tiles of a row / column may be cut by the image edge)
        r = ((rest // self.cols) * self.tile + row[n - k:] % self.tile).clamp_max(self.height - 1)
        c = ((rest % self.cols) * self.tile + col[n - k:] % self.tile).clamp_max(self.width - 1)
        view, row, col = view.clone(), row.clone(), col.clone()
        view[n - k:], row[n - k:], col[n - k:] = v, r, c
        return view, row, col

    def update(self, view: Tensor, row: Tensor, col: Tensor, ray_error: Tensor) -> None:
        """Blend each drawn ray's error ``ray_error [R]`` (>= 0, detached) into its tile; where a
        tile was drawn twice in a batch the mean of its rays' errors is blended."""
        idx = self.cells(view, row, col)
        total = torch.zeros_like(self.error).index_add_(0, idx, ray_error.float())
        count = torch.zeros_like(self.error).index_add_(0, idx, torch.ones_like(ray_error, dtype=torch.float32))
        hit = count > 0
        mean = total / count.clamp_min(1.0)
        self.error = torch.where(hit, (1.0 - BLEND) * self.error + BLEND * mean, self.error)

    def state_dict(self) -> dict:
        return {"error": self.error.detach().cpu(), "tile": self.tile}

    def load_state_dict(self, state: dict) -> None:
        """Restore a checkpoint's map; a map of another tiling (another image size) is ignored."""
        err = state.get("error")
        if err is not None and int(state.get("tile", -1)) == self.tile and err.numel() == self.error.numel():
            self.error = err.to(self.error.device, torch.float32).clone()


def ray_errors(rgb_r: Tensor, target: Tensor, mask: Tensor | None, weight_sum: Tensor) -> Tensor:
    """``[R]``: the per-ray error of the module docstring (``rgb_r, target [R, 3]`` linear,
    ``mask [R]`` 0/1 or None, ``weight_sum [R]``), detached. A non-finite render (a step the loop
    skips) scores :data:`START_ERROR`, so the map never holds a NaN (which would void every draw)."""
    with torch.no_grad():
        colour = (linear_to_srgb(rgb_r) - linear_to_srgb(target)).abs().mean(-1)
        err = colour if mask is None else colour * (mask > 0.5) + (weight_sum.clamp(0.0, 1.0) - mask).abs()
        return torch.nan_to_num(err, nan=START_ERROR, posinf=START_ERROR, neginf=START_ERROR)
