"""Per-view reading, shared by every loader and by ``validate.py``: one view decoded at a time,
brought to the working grid, checked.

The working grid of a full-size ``W x H`` view: the integer box filter ``downscale``, then
exact area resampling so that the long side is at most ``max_side`` (``resample.py``), with
``K' = S K``, ``S = diag(W'/(f W1), H'/(f H1), 1)`` (:func:`nepf_core.data.resample.grid_scale`).
Colour is averaged in linear space; masks are averaged as 0/1 values and re-thresholded at 0.5.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from nepf_core.data.errors import DatasetError
from nepf_core.color import srgb_to_linear
from nepf_core.data.images import (box_downscale, check_min_size, decode_image, mask_from_array,
                                   rgb_alpha, srgb_u8_to_linear)
from nepf_core.data.resample import area_resize, grid_scale


@dataclass
class ViewSpec:
    """One view as a loader's parser describes it, before any pixel is read.

    Attributes:
        image: image file.
        label: ``image`` relative to the dataset root (what errors name).
        K: ``[3, 3]`` float64 full-resolution intrinsics, ``Scene`` convention
           (pixel centres at +0.5).
        c2w: ``[4, 4]`` float64 OpenCV camera-to-world (world = the loader's frame).
        mask: separate mask file (DTU) or None.
        mask_label: ``mask`` relative to the root.
        expected_wh: ``(W, H)`` declared by the metadata (JSON ``w``/``h``), checked when set.
        distortion: OpenCV ``(k1, k2, p1, p2[, k3[, k4]])`` to undo while reading, or None.
    """

    image: Path
    label: str
    K: np.ndarray
    c2w: np.ndarray
    mask: Path | None = None
    mask_label: str | None = None
    expected_wh: tuple[int, int] | None = None
    distortion: tuple[float, ...] | None = None


Undistorter = Callable[[np.ndarray, np.ndarray, tuple], np.ndarray]


def to_working_grid(a: np.ndarray, downscale: int, size: tuple[int, int]) -> np.ndarray:
    """``[H, W, ...]`` -> ``[H', W', ...]`` float32: box filter by ``downscale``, then area
    resampling to ``size = (W', H')`` (each step skipped when it is the identity)."""
    a = box_downscale(a, downscale) if downscale > 1 else a
    if a.shape[1] != size[0] or a.shape[0] != size[1]:
        a = area_resize(a, *size)
    return np.asarray(a, np.float32)


def read_view(s: ViewSpec, i: int, *, downscale: int = 1, max_side: int | None = None,
              alpha_mask: bool = False, undistort: Undistorter | None = None,
              same_as: tuple[int, int] | None = None
              ) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int], bool]:
    """Decode one view: ``(rgb [h, w, 3] linear float32, mask [h, w] bool | None, (W, H) full, has_alpha)``.

    * ``rgb = srgb_to_linear(stored)`` on the working grid (module docstring); with
      ``alpha_mask`` and an RGBA file, ``rgb = srgb_to_linear(stored) * alpha`` composited
      onto black in linear space at full size, then resampled (the working image is the
      area average of the composited one), and ``mask = area(alpha) >= 0.5``.
    * ``s.mask`` files are read with :func:`mask_from_array` (luma > 127), brought to the
      working grid as 0/1 values and thresholded at 0.5; they take precedence over alpha.
    * ``undistort(arr, K, coeffs)`` is applied *after* resampling, on the working grid
      with ``K' = S K`` (the coefficients act on normalised coordinates, so they do not
      change); both filters are linear and nearly commute, and this is far cheaper. Mask files
      are undistorted the same way (as 0/1 values, re-thresholded at 0.5).

    Per-view checks (``DatasetError`` naming the file and view ``i``): decode errors,
    the size of view 0 when given as ``same_as`` (``size_mismatch``), the size declared by
    the metadata (``size_mismatch``), a mask the size of its image (``size_mismatch``), a
    non-empty mask (``empty_mask``), at least ``MIN_SIDE`` pixels on the working grid
    (``image_too_small``).
    """
    arr = decode_image(s.image, label=s.label, view=i)
    h, w = arr.shape[:2]
    if s.expected_wh is not None and (w, h) != tuple(s.expected_wh):
        raise DatasetError(f"image is {w}x{h} but the metadata says {s.expected_wh[0]}x{s.expected_wh[1]}",
                           file=s.label, view=i, code="size_mismatch")
    if same_as is not None:
        check_same_size((w, h), same_as, s.label, i)
    size, S = grid_scale(w, h, downscale, max_side)
    check_min_size(size[1], size[0], label=s.label, view=i, downscale=downscale, max_side=max_side)
    rgb, alpha = rgb_alpha(arr)
    del arr
    if rgb.dtype == np.uint8:
        rgb = srgb_u8_to_linear(rgb)
        alpha = None if alpha is None else alpha.astype(np.float32) / 255.0
    else:
        rgb = srgb_to_linear(np.asarray(rgb, dtype=np.float32))
    composite = alpha_mask and alpha is not None
    if composite:   # onto black at full size, so the resampling averages the composited image
        rgb = rgb * alpha[..., None]
    rgb = to_working_grid(rgb, downscale, size)
    alpha = None if alpha is None else to_working_grid(alpha, downscale, size)
    if undistort is not None and s.distortion is not None:
        Kd = S @ s.K
        rgb = undistort(rgb, Kd, s.distortion)
        if alpha is not None:
            alpha = undistort(alpha[..., None], Kd, s.distortion)[..., 0]
    mask = None
    if composite:
        mask = alpha >= 0.5
        if not mask.any():
            raise DatasetError("alpha channel is zero everywhere (empty mask)", file=s.label,
                               view=i, code="empty_mask")
    if s.mask is not None:
        mlabel = s.mask_label or s.mask.name
        marr = decode_image(s.mask, label=mlabel, view=i)
        if marr.shape[:2] != (h, w):
            raise DatasetError(f"mask is {marr.shape[1]}x{marr.shape[0]} but its image is {w}x{h}",
                               file=mlabel, view=i, code="size_mismatch")
        m = mask_from_array(marr)
        del marr
        mask = m if (w, h) == size else to_working_grid(m.astype(np.float32), downscale, size) >= 0.5
        if undistort is not None and s.distortion is not None:   # the mask follows its image's lens
            mask = undistort(mask.astype(np.float32)[..., None], S @ s.K, s.distortion)[..., 0] >= 0.5
        if not mask.any():
            raise DatasetError("mask is empty (no foreground pixel)", file=mlabel, view=i,
                               code="empty_mask")
    return rgb, mask, (w, h), alpha is not None


def check_downscale(downscale) -> int:
    """``downscale`` as a positive int, else ``DatasetError(code="bad_argument")``."""
    return _check_int(downscale, "downscale", 1)


def check_max_side(max_side) -> int:
    """``max_side`` as an int >= 0 (0 or None: full resolution), else ``bad_argument``."""
    return 0 if max_side is None else _check_int(max_side, "max_side", 0)


def _check_int(value, name: str, lowest: int) -> int:
    try:
        ok = not isinstance(value, bool) and int(value) == value and value >= lowest
    except (TypeError, ValueError):
        ok = False
    if not ok:
        kind = "a positive integer" if lowest == 1 else f"an integer >= {lowest}"
        raise DatasetError(f"{name} must be {kind}, got {value}", code="bad_argument")
    return int(value)


def check_same_size(wh: tuple[int, int], first_wh: tuple[int, int], label: str, i: int) -> None:
    """``size_mismatch`` unless view ``i`` has view 0's ``(W, H)``."""
    if wh != first_wh:
        raise DatasetError(f"image is {wh[0]}x{wh[1]} but view 0 is {first_wh[0]}x{first_wh[1]}",
                           file=label, view=i, code="size_mismatch")


def check_same_alpha(has: bool, first: bool, label: str, i: int) -> None:
    """``count_mismatch`` when some RGBA images (masks) mix with RGB ones (no masks)."""
    if has != first:
        raise DatasetError("some images have an alpha channel (mask) and others do not",
                           file=label, view=i, code="count_mismatch")


def iter_view_pixels(specs: list[ViewSpec], *, downscale: int = 1, max_side: int | None = None,
                     alpha_mask: bool = False, undistort: Undistorter | None = None
                     ) -> Iterator[tuple[int, np.ndarray, np.ndarray | None, tuple[int, int]]]:
    """Decode views one at a time: yields ``(i, rgb [h, w, 3], mask [h, w] | None, (W, H) full size)``.

    :func:`read_view` per view, plus the cross-view checks: every image has view 0's size
    (``size_mismatch``) and, with ``alpha_mask``, alpha in all views or none
    (``count_mismatch``). Only one view is held in memory at a time.
    """
    downscale = check_downscale(downscale)
    max_side = check_max_side(max_side)
    first = None
    for i, s in enumerate(specs):
        rgb, mask, wh, has_alpha = read_view(s, i, downscale=downscale, max_side=max_side,
                                             alpha_mask=alpha_mask, undistort=undistort,
                                             same_as=first and first[0])
        if first is None:
            first = (wh, has_alpha)
        check_same_size(wh, first[0], s.label, i)
        if alpha_mask:
            check_same_alpha(has_alpha, first[1], s.label, i)
        yield i, rgb, mask, wh


def load_view_pixels(specs: list[ViewSpec], *, downscale: int = 1, max_side: int | None = None,
                     alpha_mask: bool = False, undistort: Undistorter | None = None
                     ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Read all views into arrays (see :func:`iter_view_pixels` for the checks).

    Returns:
        images ``[N, h, w, 3]`` float32 linear, masks ``[N, h, w]`` bool or None, and
        intrinsics ``[N, 3, 3]`` float64 on the working grid (``K' = S K``, module docstring).
        With ``alpha_mask`` (and no mask files), masks are None when every pixel of every
        view is foreground: an opaque RGBA set carries no mask.
    """
    if not specs:
        raise DatasetError("the dataset has no views", code="no_views")
    images = masks = None
    opaque = True
    full_wh = None
    for i, rgb, m, wh in iter_view_pixels(specs, downscale=downscale, max_side=max_side,
                                          alpha_mask=alpha_mask, undistort=undistort):
        if images is None:
            images = np.empty((len(specs), *rgb.shape), np.float32)
            if m is not None:
                masks = np.empty((len(specs), *m.shape), bool)
            full_wh = wh
        images[i] = rgb
        if masks is not None:
            masks[i] = m
            opaque = opaque and bool(m.all())
    if alpha_mask and masks is not None and opaque and all(s.mask is None for s in specs):
        masks = None
    _, S = grid_scale(*full_wh, check_downscale(downscale), check_max_side(max_side))
    Ks = np.stack([S @ s.K for s in specs])
    return images, masks, Ks

