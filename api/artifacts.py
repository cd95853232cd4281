"""What the artifact routes serve from a job's run folder: which file a requested path names
(:func:`safe_artifact_path`) and with which content type (:func:`content_type_for`)."""

from __future__ import annotations

import mimetypes
import os

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


# moved to the storage layer (the local backend checks paths with it); kept importable from here
from jobstore.storage import PRIVATE_DIRS  # noqa: E402,F401
from jobstore.storage.local import safe_artifact_path  # noqa: E402,F401
