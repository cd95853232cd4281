"""Image files -> float arrays: decoding, sRGB transfer curves, box downscaling.

Everything here is numpy + Pillow (torch-free). Every failure raises
:class:`~nepf_core.data.errors.DatasetError` naming the file and the view.

Conventions:
    * :func:`read_image` returns the *stored* values scaled to [0, 1] (no colour transform);
      loaders then call :func:`srgb_to_linear` on the colour channels (never on alpha/masks).
    * Downscaling is a box filter by an integer factor applied to *linear* values (the
      physically meaningful average); a remainder of ``H % f`` rows / ``W % f`` columns is
      cropped from the bottom / right, which leaves pinhole intrinsics exact under
      ``K' = diag(1/f, 1/f, 1) K`` in the pixel-centres-at-+0.5 convention of ``Scene``.
    * EXIF orientation tags are ignored (as COLMAP, instant-ngp and NeRF do): cameras refer
      to the stored pixel grid.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from PIL import Image, UnidentifiedImageError

from nepf_core.data.errors import DatasetError

#: Extensions we decode. Anything else that looks like an image is rejected.
SUPPORTED_EXTS = (".png", ".jpg", ".jpeg")
#: Image-like extensions we recognise in image folders but do not support.
UNSUPPORTED_IMAGE_EXTS = (".bmp", ".tif", ".tiff", ".exr", ".hdr", ".webp", ".gif", ".heic",
                          ".heif", ".ppm", ".pgm", ".pbm", ".tga", ".dng", ".raw", ".cr2",
                          ".nef", ".jp2", ".avif", ".jxl", ".npy")
#: Smallest accepted image side (after downscaling), in pixels.
MIN_SIDE = 8

Image.MAX_IMAGE_PIXELS = 20000 * 20000  # large but finite: refuse decompression bombs


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB EOTF (IEC 61966-2-1), elementwise on values in [0, 1].

    ``lin = x / 12.92`` if ``x <= 0.04045`` else ``((x + 0.055) / 1.055) ** 2.4``.
    Worked values: 0 -> 0, 1 -> 1, 0.5 -> 0.21404.
    """
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB OETF, the inverse of :func:`srgb_to_linear`; input clipped to [0, 1].

    ``s = 12.92 x`` if ``x <= 0.0031308`` else ``1.055 x ** (1/2.4) - 0.055``.
    """
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def to_uint8(x: np.ndarray) -> np.ndarray:
    """Quantise values in [0, 1] to uint8 with rounding (values outside are clipped)."""
    return np.clip(np.round(np.asarray(x, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def is_image_name(name: str) -> bool:
    """True for a file name with a supported image extension (case-insensitive)."""
    return name.lower().endswith(SUPPORTED_EXTS)


def looks_like_image(name: str) -> bool:
    """True for a supported *or* a recognised-but-unsupported image extension."""
    low = name.lower()
    return low.endswith(SUPPORTED_EXTS) or low.endswith(UNSUPPORTED_IMAGE_EXTS)


def list_images(folder: Path, root: Path) -> list[Path]:
    """Supported images in ``folder`` sorted by name; other image types are an error.

    Hidden files (``.DS_Store``, ``._x.png`` from macOS zips) and non-image files are ignored.
    Raises ``DatasetError(code="unsupported_image")`` for e.g. a ``.bmp`` or ``.exr`` file.
    """
    out = []
    for name in sorted(os.listdir(folder)):
        p = folder / name
        if name.startswith(".") or not p.is_file():
            continue
        if is_image_name(name):
            out.append(p)
        elif looks_like_image(name):
            raise DatasetError(
                f"unsupported image format '{p.suffix}' (use PNG or JPEG)",
                file=rel(p, root), code="unsupported_image")
    return out


def rel(path: Path | str, root: Path | str) -> str:
    """``path`` relative to ``root`` as a POSIX string (or the path itself if outside)."""
    try:
        return Path(path).resolve().relative_to(Path(root).resolve()).as_posix()
    except ValueError:
        return str(path)


def decode_image(path: Path | str, *, label: str | None = None, view: int | None = None) -> np.ndarray:
    """Decode a PNG/JPEG to ``[H, W, C]``: uint8 for 8-bit files, else float32 in [0, 1].

    ``C`` is 1 (grey), 3 (RGB) or 4 (RGBA). Grey+alpha becomes RGBA, palette images become
    RGB(A), 16-bit greyscale is divided by 65535.

    Raises ``DatasetError`` with code ``missing_image``, ``unsupported_image`` or
    ``unreadable_image``, naming ``label`` (defaults to the path) and ``view``.
    """
    path = Path(path)
    label = label if label is not None else str(path)
    if not path.is_file():
        raise DatasetError("image file not found", file=label, view=view, code="missing_image")
    if not is_image_name(path.name):
        raise DatasetError(f"unsupported image format '{path.suffix or path.name}' (use PNG or JPEG)",
                           file=label, view=view, code="unsupported_image")
    try:
        with Image.open(path) as im:
            fmt = im.format
            if fmt not in ("PNG", "JPEG", "MPO"):
                raise DatasetError(f"file content is {fmt}, not PNG/JPEG", file=label, view=view,
                                   code="unsupported_image")
            im.load()
            arr = _to_array(im)
    except DatasetError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise DatasetError(f"cannot decode image: {e}", file=label, view=view,
                           code="unreadable_image") from None
    if arr.ndim != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise DatasetError("image has no pixels", file=label, view=view, code="unreadable_image")
    return arr


def read_image(path: Path | str, *, label: str | None = None, view: int | None = None) -> np.ndarray:
    """Decode a PNG/JPEG to float32 ``[H, W, C]`` in [0, 1], values as stored (no linearisation).

    See :func:`decode_image` for channels and errors.
    """
    arr = decode_image(path, label=label, view=view)
    return arr.astype(np.float32) / 255.0 if arr.dtype == np.uint8 else arr


def _to_array(im: Image.Image) -> np.ndarray:
    """Pillow image -> ``[H, W, C]`` uint8 (8-bit modes) or float32 in [0, 1]."""
    mode = im.mode
    if mode == "P":
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
    elif mode == "LA":
        im = im.convert("RGBA")
    elif mode in ("1", "L"):
        im = im.convert("L")
    elif mode in ("I;16", "I;16B", "I;16L", "I;16N"):
        a = np.asarray(im, dtype=np.float32) / 65535.0
        return a[..., None]
    elif mode in ("I", "F"):
        a = np.asarray(im, dtype=np.float64)
        vmax = 65535.0 if a.max(initial=0) > 255 else 255.0
        return (np.clip(a / vmax, 0, 1)).astype(np.float32)[..., None]
    elif mode not in ("RGB", "RGBA"):
        im = im.convert("RGB")
    a = np.asarray(im, dtype=np.uint8)
    if a.ndim == 2:
        a = a[..., None]
    return a


_SRGB_LUT = None


def srgb_u8_to_linear(x: np.ndarray) -> np.ndarray:
    """:func:`srgb_to_linear` of ``x / 255`` for uint8 ``x`` via a 256-entry table (fast)."""
    global _SRGB_LUT
    if _SRGB_LUT is None:
        _SRGB_LUT = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0)
    return _SRGB_LUT[x]


def box_downscale(a: np.ndarray, factor: int) -> np.ndarray:
    """Box filter by an integer factor: ``[H, W, ...] -> [H//f, W//f, ...]`` (mean of f x f blocks).

    The last ``H % f`` rows and ``W % f`` columns are cropped first.
    """
    if factor == 1:
        return a
    h, w = a.shape[0] // factor, a.shape[1] // factor
    rest = a.shape[2:]
    a = np.ascontiguousarray(a[: h * factor, : w * factor], dtype=np.float32)
    a = a.reshape(h, factor, -1).sum(1)  # rows: contiguous reductions are fast
    a = a.reshape(h, w, factor, *rest).sum(2)
    return a / np.float32(factor * factor)


def rgb_alpha(arr: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Split ``[H, W, C]`` stored values into ``rgb [H, W, 3]`` and ``alpha [H, W]`` (or None)."""
    c = arr.shape[-1]
    if c == 1:
        return np.repeat(arr, 3, axis=-1), None
    if c == 4:
        return arr[..., :3], arr[..., 3]
    return arr[..., :3], None


def mask_from_array(arr: np.ndarray) -> np.ndarray:
    """Stored mask values ``[H, W, C]`` (uint8, or float in [0, 1]) -> bool ``[H, W]``.

    Colour masks are converted to luma L = (299 R + 587 G + 114 B) / 1000 (Pillow's ``L``)
    and thresholded at 127 (``L > 127`` in 8-bit units), which removes soft edges and
    channel noise. An alpha channel, when present, is ignored: masks are stored as values.
    """
    if arr.dtype == np.uint8:
        if arr.shape[-1] >= 3:
            a = arr.astype(np.int32)
            return (299 * a[..., 0] + 587 * a[..., 1] + 114 * a[..., 2]) > 127 * 1000 + 500
        return arr[..., 0] > 127
    if arr.shape[-1] >= 3:
        lum = (299.0 * arr[..., 0] + 587.0 * arr[..., 1] + 114.0 * arr[..., 2]) / 1000.0
    else:
        lum = arr[..., 0]
    return lum * 255.0 > 127.5


def check_min_size(h: int, w: int, *, label: str, view: int | None, downscale: int) -> None:
    """Raise ``image_too_small`` when either side is below :data:`MIN_SIDE` after downscaling."""
    if h < MIN_SIDE or w < MIN_SIDE:
        extra = f" after downscale {downscale}" if downscale > 1 else ""
        raise DatasetError(f"image is {w}x{h}{extra}; at least {MIN_SIDE}x{MIN_SIDE} pixels needed",
                           file=label, view=view, code="image_too_small")


# --------------------------------------------------------------------------------------
# Per-view reading, shared by every loader and by validate.py
# --------------------------------------------------------------------------------------



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
        distortion: OpenCV ``(k1, k2, p1, p2, k3)`` to undo while reading, or None.
    """

    image: Path
    label: str
    K: np.ndarray
    c2w: np.ndarray
    mask: Path | None = None
    mask_label: str | None = None
    expected_wh: tuple[int, int] | None = None
    distortion: tuple[float, float, float, float, float] | None = None


Undistorter = Callable[[np.ndarray, np.ndarray, tuple], np.ndarray]


def read_view(s: ViewSpec, i: int, *, downscale: int = 1, alpha_mask: bool = False,
              undistort: Undistorter | None = None, same_as: tuple[int, int] | None = None
              ) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int], bool]:
    """Decode one view: ``(rgb [h, w, 3] linear float32, mask [h, w] bool | None, (W, H) full, has_alpha)``.

    * ``rgb = srgb_to_linear(stored)``; with ``alpha_mask`` and an RGBA file,
      ``rgb = srgb_to_linear(stored) * alpha`` (composited onto black in linear space) and
      ``mask = box(alpha) >= 0.5``.
    * ``s.mask`` files are read with :func:`mask_from_array` (luma > 127); they take
      precedence over alpha.
    * ``undistort(arr, K, coeffs)`` is applied *after* the box filter, on the downscaled grid
      with ``K' = diag(1/f, 1/f, 1) K`` (the coefficients act on normalised coordinates, so
      they do not change); both filters are linear and nearly commute, and this is f^2
      times cheaper.

    Per-view checks (``DatasetError`` naming the file and view ``i``): decode errors,
    the size of view 0 when given as ``same_as`` (``size_mismatch``), the size declared by the metadata (``size_mismatch``), a mask the size of its image
    (``size_mismatch``), a non-empty mask (``empty_mask``), at least :data:`MIN_SIDE`
    pixels after downscaling (``image_too_small``).
    """
    arr = decode_image(s.image, label=s.label, view=i)
    h, w = arr.shape[:2]
    if s.expected_wh is not None and (w, h) != tuple(s.expected_wh):
        raise DatasetError(f"image is {w}x{h} but the metadata says {s.expected_wh[0]}x{s.expected_wh[1]}",
                           file=s.label, view=i, code="size_mismatch")
    if same_as is not None:
        check_same_size((w, h), same_as, s.label, i)
    check_min_size(h // downscale, w // downscale, label=s.label, view=i, downscale=downscale)
    rgb, alpha = rgb_alpha(arr)
    del arr
    if rgb.dtype == np.uint8:
        rgb = srgb_u8_to_linear(rgb)
        alpha = None if alpha is None else alpha.astype(np.float32) / 255.0
    else:
        rgb = srgb_to_linear(rgb)
    rgb = box_downscale(rgb, downscale)
    alpha = None if alpha is None else box_downscale(alpha, downscale)
    if undistort is not None and s.distortion is not None:
        Kd = np.diag([1.0 / downscale, 1.0 / downscale, 1.0]) @ s.K
        rgb = undistort(rgb, Kd, s.distortion)
        if alpha is not None:
            alpha = undistort(alpha[..., None], Kd, s.distortion)[..., 0]
    mask = None
    if alpha_mask and alpha is not None:
        rgb = rgb * alpha[..., None]
        mask = alpha >= 0.5
        if not mask.any():
            raise DatasetError("alpha channel is zero everywhere (empty mask)", file=s.label,
                               view=i, code="empty_mask")
    if s.mask is not None:
        mlabel = s.mask_label or str(s.mask)
        marr = decode_image(s.mask, label=mlabel, view=i)
        if marr.shape[:2] != (h, w):
            raise DatasetError(f"mask is {marr.shape[1]}x{marr.shape[0]} but its image is {w}x{h}",
                               file=mlabel, view=i, code="size_mismatch")
        m = mask_from_array(marr)
        mask = m if downscale == 1 else box_downscale(m.astype(np.float32), downscale) >= 0.5
        if not mask.any():
            raise DatasetError("mask is empty (no foreground pixel)", file=mlabel, view=i,
                               code="empty_mask")
    return rgb, mask, (w, h), alpha is not None


def check_downscale(downscale) -> int:
    """``downscale`` as a positive int, else ``DatasetError(code="bad_argument")``."""
    try:
        ok = not isinstance(downscale, bool) and int(downscale) == downscale and downscale >= 1
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise DatasetError(f"downscale must be a positive integer, got {downscale}", code="bad_argument")
    return int(downscale)


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


def iter_view_pixels(specs: list[ViewSpec], *, downscale: int = 1, alpha_mask: bool = False,
                     undistort: Undistorter | None = None
                     ) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
    """Decode views one at a time: yields ``(i, rgb [h, w, 3], mask [h, w] | None)``.

    :func:`read_view` per view, plus the cross-view checks: every image has view 0's size
    (``size_mismatch``) and, with ``alpha_mask``, alpha in all views or none
    (``count_mismatch``). Only one view is held in memory at a time.
    """
    downscale = check_downscale(downscale)
    first = None
    for i, s in enumerate(specs):
        rgb, mask, wh, has_alpha = read_view(s, i, downscale=downscale, alpha_mask=alpha_mask,
                                             undistort=undistort, same_as=first and first[0])
        if first is None:
            first = (wh, has_alpha)
        check_same_size(wh, first[0], s.label, i)
        if alpha_mask:
            check_same_alpha(has_alpha, first[1], s.label, i)
        yield i, rgb, mask


def load_view_pixels(specs: list[ViewSpec], *, downscale: int = 1, alpha_mask: bool = False,
                     undistort: Undistorter | None = None
                     ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Read all views into arrays (see :func:`iter_view_pixels` for the checks).

    Returns:
        images ``[N, h, w, 3]`` float32 linear, masks ``[N, h, w]`` bool or None, and
        intrinsics ``[N, 3, 3]`` float64 scaled to the downscaled grid
        (``K' = diag(1/f, 1/f, 1) K``).
        With ``alpha_mask`` (and no mask files), masks are None when every pixel of every
        view is foreground: an opaque RGBA set carries no mask.
    """
    if not specs:
        raise DatasetError("the dataset has no views", code="no_views")
    images = masks = None
    opaque = True
    for i, rgb, m in iter_view_pixels(specs, downscale=downscale, alpha_mask=alpha_mask,
                                      undistort=undistort):
        if images is None:
            images = np.empty((len(specs), *rgb.shape), np.float32)
            if m is not None:
                masks = np.empty((len(specs), *m.shape), bool)
        images[i] = rgb
        if masks is not None:
            masks[i] = m
            opaque = opaque and bool(m.all())
    if alpha_mask and masks is not None and opaque and all(s.mask is None for s in specs):
        masks = None
    f = float(downscale)
    S = np.diag([1.0 / f, 1.0 / f, 1.0])
    Ks = np.stack([S @ s.K for s in specs])
    return images, masks, Ks
