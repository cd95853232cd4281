"""The content type an artifact is served with (:func:`content_type_for`). Which file or object a
requested path names, and that it stays inside the run folder, is the storage layer's business
(:func:`jobstore.storage.artifact_rel`, :func:`jobstore.storage.local.safe_artifact_path`)."""

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

