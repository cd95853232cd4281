"""Image files -> float arrays: decoding, box downscaling (the sRGB curves: :mod:`nepf_core.color`).

(Per-view reading on the working grid is in ``views.py``; area resampling in ``resample.py``.)

Everything here is numpy + Pillow (torch-free). Every failure raises
:class:`~nepf_core.data.errors.DatasetError` naming the file and the view.

Conventions:
    * :func:`read_image` returns the *stored* values scaled to [0, 1] (no colour transform);
      loaders then call :func:`nepf_core.color.srgb_to_linear` (float32) on the colour channels (never on alpha/masks).
    * Downscaling is a box filter by an integer factor applied to *linear* values (the
      physically meaningful average); a remainder of ``H % f`` rows / ``W % f`` columns is
      cropped from the bottom / right, which leaves pinhole intrinsics exact under
      ``K' = diag(1/f, 1/f, 1) K`` in the pixel-centres-at-+0.5 convention of ``Scene``.
    * EXIF orientation tags are ignored (as COLMAP, instant-ngp and NeRF do): cameras refer
      to the stored pixel grid.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from nepf_core.color import srgb_to_linear
from nepf_core.data.errors import DatasetError
from nepf_core.data.paths import dataset_path, rel

#: Extensions we decode. Anything else that looks like an image is rejected.
SUPPORTED_EXTS = (".png", ".jpg", ".jpeg")
#: Image-like extensions we recognise in image folders but do not support.
UNSUPPORTED_IMAGE_EXTS = (".bmp", ".tif", ".tiff", ".exr", ".hdr", ".webp", ".gif", ".heic",
                          ".heif", ".ppm", ".pgm", ".pbm", ".tga", ".dng", ".raw", ".cr2",
                          ".nef", ".jp2", ".avif", ".jxl", ".npy")
#: Smallest accepted image side (after downscaling), in pixels.
MIN_SIDE = 8

Image.MAX_IMAGE_PIXELS = 20000 * 20000  # large but finite: refuse decompression bombs


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
    Every entry must resolve inside ``root`` (a symbolic link out of it is
    ``path_outside_dataset``, checked before the entry's type, see ``paths.py``).
    Raises ``DatasetError(code="unsupported_image")`` for e.g. a ``.bmp`` or ``.exr`` file.
    """
    out = []
    folder_label = rel(folder, root)
    for name in sorted(os.listdir(folder)):
        if name.startswith("."):
            continue
        written = name if folder_label == "." else f"{folder_label}/{name}"
        p = dataset_path(root, written, file=written)
        if not p.is_file():
            continue
        if is_image_name(name):
            out.append(p)
        elif looks_like_image(name):
            raise DatasetError(
                f"unsupported image format '{p.suffix}' (use PNG or JPEG)",
                file=written, code="unsupported_image")
    return out


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
    except UnidentifiedImageError:
        raise DatasetError("cannot decode image: not a PNG/JPEG file Pillow can identify", file=label,
                           view=view, code="unreadable_image") from None
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        why = e.strerror if isinstance(e, OSError) and e.filename else e  # never the server path
        raise DatasetError(f"cannot decode image: {why}", file=label, view=view,
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
        _SRGB_LUT = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0)   # float32
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


def check_min_size(h: int, w: int, *, label: str, view: int | None, downscale: int,
                   max_side: int | None = None) -> None:
    """Raise ``image_too_small`` when either side is below :data:`MIN_SIDE` on the working grid."""
    if h < MIN_SIDE or w < MIN_SIDE:
        extra = "".join([f" after downscale {downscale}" if downscale > 1 else "",
                         f" at max side {max_side}" if max_side else ""])
        raise DatasetError(f"image is {w}x{h}{extra}; at least {MIN_SIDE}x{MIN_SIDE} pixels needed",
                           file=label, view=view, code="image_too_small")
