"""``/jobs/{id}/artifacts``: the export manifest and its files, from wherever the storage layer
keeps them (:mod:`jobstore.storage`; which path may name an artifact is its business too). A file
on this machine is sent with ``FileResponse`` (Range, ETag); an object is streamed with the same
headers or, with ``NEPF_STORAGE_PRESIGN_DOWNLOADS``, answered with a 307 to a short-lived
presigned URL of that one object."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.concurrency import iterate_in_threadpool
from fastapi.responses import FileResponse, RedirectResponse, Response, StreamingResponse

from jobstore.storage import ArtifactRef

from ..artifacts import ARTIFACT_MEDIA_TYPES, content_type_for
from ..deps import OwnerDep, ServiceDep
from ..downloads import content_disposition
from ..errors import not_found
from ..queries import load_job
from ..schemas import Artifact, ArtifactList, ErrorBody

router = APIRouter(tags=["jobs"])
ERRORS = {401: {"model": ErrorBody, "description": "Missing or invalid token"},
          404: {"model": ErrorBody, "description": "No such job for this owner"}}
#: the request headers a streamed object answers (as FileResponse does for a local file)
CONDITIONAL_HEADERS = ("range", "if-range", "if-none-match")


@router.get("/jobs/{job_id}/artifacts", response_model=ArtifactList, responses=ERRORS,
            summary="The export manifest, with download URLs")
def list_artifacts(job_id: str, svc: ServiceDep, owner: OwnerDep):
    job = load_job(svc, owner, job_id)
    man = svc.storage.read_manifest(job.id)
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
def get_artifact(job_id: str, path: str, request: Request, svc: ServiceDep, owner: OwnerDep):
    job = load_job(svc, owner, job_id)
    ref = svc.storage.artifact(job.id, path)
    if ref is None:
        raise not_found("artifact")
    # a local file's type comes from its name with links resolved (as before the storage layer)
    ctype = content_type_for(ref.path.name if ref.path is not None else path.rsplit("/", 1)[-1])
    # the name a browser or a script saves the file under: "<job name>-<artifact>" (api/downloads.py)
    headers = {"Cache-Control": "private, max-age=0",
               "Content-Disposition": content_disposition(job.name, job.id, path)}
    if ref.path is not None:
        # FileResponse answers Range (206, If-Range) and sends ETag / Last-Modified
        return FileResponse(ref.path, media_type=ctype, filename=None, headers=headers)
    if svc.settings.storage_presign_downloads and ref.presign is not None:
        url = ref.presign(svc.settings.storage_presign_ttl_s, headers["Content-Disposition"], ctype)
        return RedirectResponse(url, status_code=307, headers={"Cache-Control": "no-store"})
    return stream_object(ref, request, ctype, headers)


def stream_object(ref: ArtifactRef, request: Request, ctype: str, headers: dict) -> Response:
    """The object through this process: the store answers the conditional request headers (a 304
    or 416 has no body), and the body is read in the thread pool so a slow store blocks no event loop."""
    stream = ref.open({k: request.headers[k] for k in CONDITIONAL_HEADERS if k in request.headers})
    headers = {**headers, **stream.headers}
    if stream.status in (304, 416):
        stream.close()
        return Response(status_code=stream.status, headers=headers)

    async def body():
        try:
            async for chunk in iterate_in_threadpool(stream.chunks):
                yield chunk
        finally:
            stream.close()
    return StreamingResponse(body(), status_code=stream.status, media_type=ctype, headers=headers)
