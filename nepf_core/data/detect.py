"""Which layout is this folder, and load it.

Rules, in order, for a folder ``D``:
    1. ``D`` itself is a dataset: DTU (camera npz + ``image/``) before Blender
       (``transforms_{train,test,val}.json``) before nerfstudio (``transforms.json`` with
       ``camera_model``, ``applied_transform`` or ``ply_file_path``) before instant-ngp (any other
       ``transforms.json``) before COLMAP (``sparse/0/`` or ``sparse/`` + ``images/``). So the
       folder ``ns-process-data`` writes (``transforms.json`` beside ``colmap/sparse/0``) is nerfstudio's.
    2. Otherwise look one level down (ignoring hidden folders and ``__MACOSX``), repeating
       up to :data:`MAX_DEPTH` levels while exactly one sub-folder is not a dataset: zips
       usually wrap the data in one folder. When several sub-folders are datasets (e.g. a
       scene's ``input/`` with ``dtu/`` and ``blender/``), the same preference picks one
       (the same order; ties by name).
    3. Else ``DatasetError(code="unknown_layout")``, naming the accepted layouts and the
       commands that make one from photos.
"""

from __future__ import annotations

import os
from pathlib import Path

from nepf_core.data.blender import is_blender, load_blender
from nepf_core.data.colmap import is_colmap, load_colmap
from nepf_core.data.dtu import is_dtu, load_dtu
from nepf_core.data.errors import DatasetError
from nepf_core.data.ingp import is_ingp, load_ingp
from nepf_core.data.nerfstudio import is_nerfstudio, load_nerfstudio
from nepf_core.data.scene import Scene

FORMATS = ("dtu", "blender", "nerfstudio", "ingp", "colmap")
MAX_DEPTH = 3
_CHECKS = {"dtu": is_dtu, "blender": is_blender, "nerfstudio": is_nerfstudio, "ingp": is_ingp,
           "colmap": is_colmap}
LOADERS = {"dtu": load_dtu, "blender": load_blender, "nerfstudio": load_nerfstudio, "ingp": load_ingp,
           "colmap": load_colmap}
#: What ``unknown_layout`` says: the layouts, and how to make one from photos.
UNKNOWN_LAYOUT = (
    "unknown dataset layout: expected DTU (cameras.npz or cameras_sphere.npz + image/), "
    "NeRF-synthetic (transforms_train.json), nerfstudio or instant-ngp (transforms.json), or COLMAP "
    "(sparse/0/ with cameras, images, points3D .bin or .txt + images/). From photos alone, make one with "
    "`colmap automatic_reconstructor --workspace_path DIR --image_path DIR/images` (COLMAP) or "
    "`ns-process-data images --data PHOTOS --output-dir DIR` (nerfstudio)")


def format_of(folder: Path) -> str | None:
    """The layout of ``folder`` itself (no descent), or None."""
    for fmt in FORMATS:
        if _CHECKS[fmt](folder):
            return fmt
    return None


def _subdirs(folder: Path) -> list[Path]:
    try:
        names = sorted(os.listdir(folder))
    except OSError:
        return []
    return [folder / n for n in names
            if not n.startswith((".", "__MACOSX")) and (folder / n).is_dir()]


def resolve_dataset(root: Path | str) -> tuple[str, Path]:
    """``(format, dataset folder)`` for ``root`` following the module rules."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError("dataset folder not found", file=str(root), code="unknown_layout")
    folder = root
    for _ in range(MAX_DEPTH + 1):
        fmt = format_of(folder)
        if fmt is not None:
            return fmt, folder
        subs = _subdirs(folder)
        found = [(FORMATS.index(f), s.name, f, s) for s in subs if (f := format_of(s)) is not None]
        if found:
            _, _, fmt, sub = min(found)
            return fmt, sub
        if len(subs) != 1:
            break
        folder = subs[0]
    raise DatasetError(UNKNOWN_LAYOUT, file=os.path.relpath(folder, root) if folder != root else ".",
                       code="unknown_layout")


def detect_format(root: Path | str) -> str:
    """One of :data:`FORMATS` for a dataset folder (see module rules)."""
    return resolve_dataset(root)[0]


def load_scene(root: Path | str, split: str = "train", *, downscale: int = 1,
               max_views: int | None = None, max_side: int | None = None,
               max_total_pixels: int | None = None) -> Scene:
    """Detect the layout of ``root`` and load ``split`` as a :class:`Scene`.

    Args:
        root: dataset folder (or a folder wrapping one, see module rules).
        split: ``"train"`` (default); ``"test"``/``"val"`` for Blender; ``"all"`` (same views
            as ``"train"``) for DTU, nerfstudio, instant-ngp and COLMAP, which have no splits.
        downscale: integer box-filter factor (e.g. 4 for real DTU at 1600x1200).
        max_views: keep at most this many evenly spaced views.
        max_side: working resolution: views whose long side (after ``downscale``) exceeds it
            are area-resampled to it, intrinsics scaled to match (``views.py``); 0/None: full size.
        max_total_pixels: refuse (``too_many_pixels``) a split whose images hold more pixels,
            read from the headers before decoding (``budget.py``); None: no limit.

    Every file the dataset names must resolve inside the dataset folder (``paths.py``).
    """
    fmt, folder = resolve_dataset(root)
    return LOADERS[fmt](folder, split, downscale=downscale, max_views=max_views, max_side=max_side,
                        max_total_pixels=max_total_pixels)
