"""Containment: every file a dataset names lies inside the dataset's own folder.

A dataset is untrusted input: a ``transforms.json`` frame may say ``/etc/x.png`` or
``../../other_job/image/000.png``, and a file or folder may be a symbolic link to anywhere.
On a shared server that would let one user's job read another user's images. So every
referenced path is checked the same way, by :func:`dataset_path`:

    ``resolved = (base / written).resolve()``  (symbolic links followed, ``..`` collapsed)
    accepted iff ``resolved`` is ``root.resolve()`` or lies under it.

The check runs *before* any existence check, and its error names the frame and the path
as written in the dataset, never the resolved server path. So a file outside the folder
gives the same message whether it exists or not: the error is no file-existence oracle.

:func:`rel` gives the labels that errors and ``Scene.names`` carry: lexical paths relative
to the root (no symlink resolution, so a label is what the user wrote or listed), and
never an absolute path.
"""

from __future__ import annotations

import os
from pathlib import Path

from nepf_core.data.errors import DatasetError


def rel(path: Path | str, root: Path | str) -> str:
    """``path`` relative to ``root`` as a POSIX string, computed lexically.

    Falls back to the file name when ``path`` is not under ``root`` lexically, so a label
    is never an absolute server path.
    """
    r = os.path.relpath(os.path.abspath(path), os.path.abspath(root))
    if r == os.pardir or r.startswith(os.pardir + os.sep):
        return Path(path).name
    return Path(r).as_posix()


def is_inside(root: Path | str, path: Path | str) -> bool:
    """True when ``path``, after resolving symbolic links and ``..``, is ``root`` or under it.

    An unresolvable path (a symbolic-link loop) counts as outside.
    """
    try:
        resolved = Path(path).resolve()
    except (OSError, RuntimeError, ValueError):
        return False
    return resolved.is_relative_to(Path(root).resolve())


def dataset_path(root: Path | str, written: str, *, base: Path | str | None = None,
                 file: str | None = None, view: int | None = None) -> Path:
    """``base / written`` (``base`` defaults to ``root``) once it is known to resolve inside ``root``.

    Args:
        root: the dataset folder.
        written: the path exactly as the dataset names it (a JSON ``file_path``, a folder
            entry such as ``image/000.png``); may be absolute or contain ``..``.
        base: the folder ``written`` is relative to (a JSON file's folder).
        file, view: where the reference was written (the JSON file, the frame index), for the error.

    Returns the joined, unresolved path (labels come from it with :func:`rel`).
    Raises ``DatasetError(code="path_outside_dataset")`` naming ``written``, never the
    resolved target, whether or not the target exists.
    """
    if "\x00" in written:
        raise DatasetError(f"the path {written!r} contains a NUL character", file=file, view=view,
                           code="bad_json")
    joined = Path(base if base is not None else root) / written
    if not is_inside(root, joined):
        raise DatasetError(f"the path '{written}' points outside the dataset folder; every file a "
                           "dataset names must be inside it", file=file, view=view,
                           code="path_outside_dataset")
    return joined


def existing_file(root: Path | str, name: str) -> Path | None:
    """``root / name`` if it is a file inside ``root``; a symbolic link out of it is an error
    (:func:`dataset_path`), whatever it points at."""
    p = dataset_path(root, name, file=name)
    return p if p.is_file() else None


def existing_dir(root: Path | str, name: str) -> Path | None:
    """``root / name`` if it is a folder inside ``root`` (see :func:`existing_file`)."""
    p = dataset_path(root, name, file=name)
    return p if p.is_dir() else None
