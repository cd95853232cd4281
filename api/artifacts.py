"""What the artifact routes serve from a job's run folder: which file a requested path names
(:func:`safe_artifact_path`) and with which content type (:func:`content_type_for`)."""

from __future__ import annotations

import mimetypes
import os
from pathlib import Path
from typing import Optional

CONTENT_TYPES = {".glb": "model/gltf-binary", ".gltf": "model/gltf+json", ".ply": "application/octet-stream",
                 ".obj": "model/obj", ".mtl": "model/mtl", ".png": "image/png", ".jpg": "image/jpeg",
                 ".jpeg": "image/jpeg", ".json": "application/json", ".jsonl": "application/x-ndjson",
                 ".exr": "image/x-exr", ".npz": "application/octet-stream", ".npy": "application/octet-stream",
                 ".txt": "text/plain; charset=utf-8", ".csv": "text/csv; charset=utf-8",
                 ".mp4": "video/mp4", ".html": "text/html; charset=utf-8", ".pt": "application/octet-stream"}


#: every media type the artifact route serves (declared in its OpenAPI 200 response)
ARTIFACT_MEDIA_TYPES = sorted({t.split(";")[0] for t in CONTENT_TYPES.values()})


def content_type_for(path: str) -> str:
    ext = os.path.splitext(path)[1].lower()
    return CONTENT_TYPES.get(ext) or mimetypes.guess_type(path)[0] or "application/octet-stream"


#: the run folder's sub-folder that is never served (resume state, not an asset)
PRIVATE_DIRS = ("checkpoints",)


def safe_artifact_path(base: Path, rel: str) -> Optional[Path]:
    """``base/rel`` if it is a regular file inside ``base`` and outside ``checkpoints/``; else None.

    Both tests are made on the path with every link resolved, not on the path as written: a
    link inside the run folder (``x.pt -> checkpoints/latest.pt``) must not serve what its target
    would not (issue 37). The written form is checked too, so a 404 does not depend on whether
    the file exists."""
    if not rel or "\x00" in rel or rel.startswith(("/", "\\")) or "\\" in rel:
        return None
    parts = rel.split("/")
    if any(p in ("", ".", "..") for p in parts) or parts[0] in PRIVATE_DIRS:
        return None
    try:
        root = base.resolve(strict=True)
        target = (base / rel).resolve(strict=True)
    except (OSError, RuntimeError, ValueError):
        return None
    if root not in target.parents or not target.is_file():
        return None
    if target.relative_to(root).parts[0] in PRIVATE_DIRS:
        return None
    return target
