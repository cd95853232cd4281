"""From parsed views to a :class:`Scene`: the steps every loader takes after its parser.

A loader's parser describes the views (:class:`~nepf_core.data.views.ViewSpec`: image, ``K``,
``c2w`` in the dataset's world) without reading a pixel. Then, in this order:

1. the decoded-pixel budget is checked from the image headers of every view (``budget.py``);
2. the normalisation is found (DTU: ``scale_mat``, or from the loaded cameras; COLMAP and
   transforms.json: from every view of the normalisation split at a small working size,
   :func:`read_normalized_views`, before any view is left out);
3. ``max_views`` keeps evenly spaced views (:func:`pick_views`);
4. the kept views are read on the working grid (:func:`nepf_core.data.views.load_view_pixels`);
5. the cameras go into the normalised frame and the :class:`Scene` is built
   (:func:`scene_from_views`).

Formats without splits (DTU, COLMAP, nerfstudio, instant-ngp) take ``split`` ``"train"`` or
``"all"`` and return every view (:func:`check_whole_set`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from nepf_core.data.budget import check_total_pixels
from nepf_core.data.errors import DatasetError
from nepf_core.data.normalize import Normalization, c2w_to_normalized
from nepf_core.data.scene import Scene
from nepf_core.data.views import Undistorter, ViewSpec, load_view_pixels


def check_whole_set(split: str, folders: str, views_are: str, file: str) -> None:
    """``missing_split`` unless ``split`` is ``"train"`` or ``"all"``: ``folders`` (e.g. "DTU")
    have no splits, ``views_are`` says what the training views are ("all views")."""
    if split not in ("train", "all"):
        raise DatasetError(f"{folders} folders have no '{split}' split ({views_are} are training views)",
                           file=file, code="missing_split")


def pick_views(n: int, max_views: int | None) -> np.ndarray:
    """Evenly spaced view indices: all ``n`` or ``round(linspace(0, n-1, max_views))``."""
    if max_views is None or max_views >= n:
        return np.arange(n)
    if max_views < 1:
        raise DatasetError(f"max_views must be >= 1, got {max_views}", code="bad_argument")
    return np.unique(np.round(np.linspace(0, n - 1, max_views)).astype(np.int64))


@dataclass
class LoadedViews:
    """The views kept and their pixels on the working grid: ``images [N, h, w, 3]`` float32
    linear, ``masks [N, h, w]`` bool or None, ``Ks [N, 3, 3]`` float64 (working grid)."""

    specs: list[ViewSpec]
    images: np.ndarray
    masks: np.ndarray | None
    Ks: np.ndarray

    def c2w(self) -> np.ndarray:
        """``[N, 4, 4]`` float64 camera-to-world in the parser's frame."""
        return np.stack([s.c2w for s in self.specs])


def read_views(specs: list[ViewSpec], *, max_views: int | None, downscale: int, max_side: int | None,
               alpha_mask: bool = False, undistort: Undistorter | None = None) -> LoadedViews:
    """Steps 3 and 4: keep ``max_views`` evenly spaced views and read them (``alpha_mask``: an
    RGBA image's alpha is its mask; ``undistort``: applied to views with distortion)."""
    specs = [specs[i] for i in pick_views(len(specs), max_views)]
    images, masks, Ks = load_view_pixels(specs, downscale=downscale, max_side=max_side, alpha_mask=alpha_mask,
                                         undistort=undistort)
    return LoadedViews(specs, images, masks, Ks)


def read_normalized_views(specs: list[ViewSpec], normalization: Callable[[], Normalization], *,
                          max_views: int | None, max_total_pixels: int | None, downscale: int,
                          max_side: int | None) -> tuple[LoadedViews, np.ndarray, Normalization]:
    """Steps 1-4 for COLMAP and transforms.json: ``(views, c2w [N, 4, 4] in the normalised frame,
    normalisation)``. ``normalization()`` is called after the budget check (it reads the
    images' alpha); the views are undistorted and take their alpha as masks."""
    from nepf_core.data.ingp import undistort_image   # ingp -> blender -> this module

    check_total_pixels([s.image for s in specs], max_total_pixels)
    norm = normalization()
    views = read_views(specs, max_views=max_views, downscale=downscale, max_side=max_side, alpha_mask=True,
                       undistort=undistort_image)
    return views, c2w_to_normalized(views.c2w(), norm.world_from_norm), norm


def scene_from_views(views: LoadedViews, c2w: np.ndarray, world_from_norm: np.ndarray, *, root: Path | str,
                     source_format: str, split: str, extras: dict, points: np.ndarray | None = None) -> Scene:
    """Step 5: the :class:`Scene` of ``views`` with cameras ``c2w [N, 4, 4]`` (normalised frame);
    intrinsics and cameras stored as float32, each view named by its image's label."""
    return Scene(images=views.images, masks=views.masks, intrinsics=views.Ks.astype(np.float32),
                 c2w=c2w.astype(np.float32), world_from_norm=world_from_norm, names=[s.label for s in views.specs],
                 root=str(root), source_format=source_format, split=split, extras=extras, points=points)
