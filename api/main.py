"""The FastAPI application: ``create_app()``; ``uvicorn api.main:app`` uses the environment."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Optional

from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from jobstore.engine import ping as ping_store
from jobstore.queue import ping_broker
from jobstore.reconcile import Reconciler
from jobstore.storage import StorageUnavailable

from .body_limit import BodyLimit, upload_body_cap, upload_too_large
from .header_limit import HeaderLimit
from .errors import ApiError, api_error_handler, http_error_handler, internal_error_handler, storage_error_handler
from .routes import artifacts, events, jobs
from .schemas import Health
from .service import Service
from jobstore.settings import Settings, get_settings

log = logging.getLogger("nepf.api")
REPO_ROOT = Path(__file__).resolve().parent.parent

PLACEHOLDER = """<!doctype html><meta charset=utf-8><title>NePF</title>
<h1>NePF service</h1><p>The web viewer is not built (run <code>npm run build</code> in <code>web/</code>).
See the API at <a href="/docs">/docs</a>.</p>"""


def create_app(settings: Optional[Settings] = None, *, reconciler: Optional[bool] = None) -> FastAPI:
    settings = settings or get_settings()
    svc = Service.create(settings)
    run_reconciler = settings.reconcile_interval_s > 0 if reconciler is None else reconciler

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        if run_reconciler:
            svc.reconciler = Reconciler(settings, svc.Session, svc.celery)
            svc.reconciler.start()
        try:
            yield
        finally:
            if svc.reconciler is not None:
                svc.reconciler.stop()

    app = FastAPI(title="NePF jobs API", version="0.1.0", lifespan=lifespan,
                  description="Upload a dataset zip, train NePF, download the relightable asset. "
                              "Auth: `Authorization: Bearer <token>` (`nepf token create NAME`).")
    app.state.service = svc
    app.add_exception_handler(ApiError, api_error_handler)
    app.add_exception_handler(StarletteHTTPException, http_error_handler)
    app.add_exception_handler(StorageUnavailable, storage_error_handler)
    app.add_exception_handler(Exception, internal_error_handler)
    app.add_middleware(BodyLimit, caps={("POST", "/jobs"): upload_body_cap(settings)},
                       error=lambda: upload_too_large(settings))
    if settings.cors_origins.strip():
        from fastapi.middleware.cors import CORSMiddleware
        app.add_middleware(CORSMiddleware, allow_origins=[o.strip() for o in settings.cors_origins.split(",")],
                           allow_methods=["*"], allow_headers=["*"],
                           # a viewer on another origin reads the download's name and its validators
                           expose_headers=["Content-Disposition", "ETag", "Last-Modified", "Content-Range"])
    # outermost: a head over the cap is refused before CORS, the body cap or any route sees it
    app.add_middleware(HeaderLimit, limit=settings.max_header_bytes)
    for routes in (jobs, events, artifacts):
        app.include_router(routes.router)

    @app.get("/healthz", response_model=Health, tags=["health"], summary="The process is up")
    def healthz():
        return Health(ok=True)

    @app.get("/readyz", response_model=Health, tags=["health"], responses={503: {"model": Health}},
             summary="The job store and the broker answer")
    async def readyz():
        checks: dict = {}
        ok = True
        for name, fn in (("database", lambda: ping_store(settings.db_url)),
                         ("broker", lambda: ping_broker(svc.celery)), ("storage", svc.storage.ping)):
            try:
                await run_in_threadpool(fn)
                checks[name] = "ok"
            except Exception as exc:  # noqa: BLE001 - report, do not raise
                ok = False
                checks[name] = f"error: {type(exc).__name__}: {exc}"[:300]
        checks["broker_kind"] = "embedded-sqlite" if settings.embedded else "external"
        body = Health(ok=ok, checks=checks)
        return JSONResponse(body.model_dump(), status_code=200 if ok else 503)

    web_dir = settings.web_dir or (REPO_ROOT / "web" / "dist")
    if Path(web_dir).is_dir():
        # mounted last: every API route above takes precedence over the static files
        app.mount("/", StaticFiles(directory=str(web_dir), html=True), name="web")
    else:
        @app.get("/", include_in_schema=False)
        def index():
            return HTMLResponse(PLACEHOLDER)
    return app


def __getattr__(name: str):
    # ``uvicorn api.main:app`` builds the app lazily from the environment
    if name == "app":
        return create_app()
    raise AttributeError(name)
