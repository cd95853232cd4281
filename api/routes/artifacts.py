"""``/jobs/{id}/artifacts``: the export manifest and its files. Which file a path names, and
that it stays inside the run folder, is :func:`api.artifacts.safe_artifact_path`'s business."""

from __future__ import annotations

import json
from typing import Optional

from fastapi import APIRouter
from fastapi.responses import FileResponse

from ..artifacts import ARTIFACT_MEDIA_TYPES, content_type_for, safe_artifact_path
from ..deps import OwnerDep, ServiceDep
from ..downloads import content_disposition
from ..errors import not_found
from ..queries import load_job, run_dir
from ..schemas import Artifact, ArtifactList, ErrorBody

router = APIRouter(tags=["jobs"])
ERRORS = {401: {"model": ErrorBody, "description": "Missing or invalid token"},
          404: {"model": ErrorBody, "description": "No such job for this owner"}}


def read_manifest(svc, job_id: str) -> Optional[dict]:
    try:
        data = json.loads((run_dir(svc, job_id) / "manifest.json").read_text())
        return data if isinstance(data, dict) else None
    except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError):
        return None


@router.get("/jobs/{job_id}/artifacts", response_model=ArtifactList, responses=ERRORS,
            summary="The export manifest, with download URLs")
def list_artifacts(job_id: str, svc: ServiceDep, owner: OwnerDep):
    job = load_job(svc, owner, job_id)
    man = read_manifest(svc, job.id)
    items = []
    for a in (man or {}).get("artifacts", []) or []:
        if not isinstance(a, dict) or not isinstance(a.get("path"), str):
            continue
        p = a["path"]
        items.append(Artifact(kind=a.get("kind"), path=p, bytes=a.get("bytes"), sha256=a.get("sha256"),
                              content_type=content_type_for(p), url=f"/jobs/{job.id}/artifacts/{p}"))
    frame = (man or {}).get("frame")
    return ArtifactList(artifacts=items, manifest=man is not None, status=job.status,
                        frame=frame if isinstance(frame, dict) else None)


@router.get("/jobs/{job_id}/artifacts/{path:path}", responses={**ERRORS, 200: {
    "content": {t: {} for t in ARTIFACT_MEDIA_TYPES}, "description": "The file, with its content type"}},
    response_class=FileResponse, summary="Download one artifact (asset.glb, textures, previews, metrics...) as "
                                         "an attachment named <job name>-<artifact>; Range and ETag supported")
def get_artifact(job_id: str, path: str, svc: ServiceDep, owner: OwnerDep):
    job = load_job(svc, owner, job_id)
    target = safe_artifact_path(run_dir(svc, job.id), path)
    if target is None:
        raise not_found("artifact")
    # FileResponse answers Range (206, If-Range) and sends ETag / Last-Modified; the name a browser
    # or a script saves the file under: "<job name>-<artifact>" (api/downloads.py)
    return FileResponse(target, media_type=content_type_for(target.name), filename=None,
                        headers={"Cache-Control": "private, max-age=0",
                                 "Content-Disposition": content_disposition(job.name, job.id, path)})
