"""The decoded-pixel budget of a dataset, checked from the image headers before any decoding.

Views are decoded one at a time and brought to the working resolution, so what a dataset
costs to load is dominated by the *decode* of its full-size images: the sum over views of
``W x H`` of the colour images (a view's mask is decoded beside it, one at a time, and is
not counted). Pillow opens files lazily, so the sizes come from the headers: a dataset over
the budget is refused without decoding one pixel.
"""

from __future__ import annotations

from pathlib import Path

from PIL import Image

from nepf_core.data.errors import DatasetError


def image_size(path: Path | str) -> tuple[int, int] | None:
    """``(W, H)`` from the file's header, or None when it cannot be read (the decode that
    follows reports that error with its own code)."""
    try:
        with Image.open(path) as im:
            return im.size
    except Exception:  # noqa: BLE001 - Pillow raises many types for unreadable headers
        return None


def total_pixels(images: list[Path]) -> int:
    """``sum W x H`` over ``images`` (unreadable headers count 0)."""
    total = 0
    for p in images:
        wh = image_size(p)
        if wh is not None:
            total += wh[0] * wh[1]
    return total


def check_total_pixels(images: list[Path], limit: int | None) -> int:
    """Raise ``too_many_pixels`` when the images hold more than ``limit`` pixels (None/0: no limit).

    Returns the total, ``sum W x H`` over ``images``.
    """
    total = total_pixels(images)
    if limit and total > limit:
        raise DatasetError(f"the {len(images)} images hold {total:,} pixels in all, above the limit of "
                           f"{int(limit):,} decoded pixels per dataset; use fewer or smaller images",
                           code="too_many_pixels")
    return total
