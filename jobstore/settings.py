"""Service settings, read by the API and the worker alike: every knob is an ``NEPF_*`` environment variable (pydantic-settings).

The full table with defaults lives in ``docs/SERVICE.md``; ``tests/test_api_settings.py`` checks
that every variable set by ``docker-compose.yml`` / ``Dockerfile`` is one of these.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal, Optional

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

# the one nepf_core module the API imports: two constants, stdlib only (no torch), shared with the CLI
from nepf_core.limits import DEFAULT_IMAGE_SIDE, MAX_TOTAL_PIXELS


class Settings(BaseSettings):
    """NePF service settings (environment prefix ``NEPF_``)."""

    model_config = SettingsConfigDict(env_prefix="NEPF_", extra="ignore")

    # --- storage -------------------------------------------------------------------------
    data_dir: Path = Field(Path("./nepf-data"), description="Job folders, SQLite DB, embedded broker.")
    database_url: Optional[str] = Field(
        None, description="SQLAlchemy URL of the job store; default sqlite:///DATA_DIR/nepf.sqlite3.")
    broker_url: Optional[str] = Field(
        None, description="Celery broker (redis://...). Unset: embedded SQLite broker + local worker.")
    secret_key: Optional[str] = Field(
        None, description="HMAC key for SSE tickets; default: random, kept in DATA_DIR/secret.key "
                          "(required with NEPF_STORAGE_URL: every API replica must share it).")
    storage_url: Optional[str] = Field(
        None, pattern=r"^s3://[^/]+(/.*)?$",
        description="s3://bucket/prefix: datasets, checkpoints, metrics and artifacts live in this bucket "
                    "(AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_DEFAULT_REGION); "
                    "unset: in DATA_DIR/jobs.")
    storage_sync_s: float = Field(2.0, gt=0, description="How often a worker uploads a job's new metrics to the store.")
    storage_wait_s: float = Field(
        3600.0, ge=0, description="How long a job waits for an unreachable object store (at its start, "
                                  "and to store its results) before it fails.")
    storage_presign_downloads: bool = Field(
        False, description="Artifact downloads answer 307 to a presigned GET of the store instead of "
                           "streaming through the API (the store must be reachable by the clients).")
    storage_presign_ttl_s: int = Field(300, ge=1, le=604800, description="Lifetime of a presigned download URL.")

    # --- uploads -------------------------------------------------------------------------
    max_upload_mb: float = Field(2048.0, description="Cap on the uploaded zip (streamed to disk).")
    max_unzipped_mb: float = Field(8192.0, description="Cap on the total uncompressed size of the zip.")
    max_zip_ratio: float = Field(200.0, description="Cap on uncompressed/compressed size, per entry and total.")
    max_zip_entries: int = Field(10000, description="Cap on the number of entries in the zip.")
    max_image_pixels: int = Field(50_000_000, description="Pillow pixel limit (image-bomb guard).")
    max_total_pixels: int = Field(
        MAX_TOTAL_PIXELS, ge=0, description="Cap on the decoded pixels of a dataset's images, all views together, "
                                       "read from the headers before decoding (0: none).")
    max_image_side: int = Field(
        1600, ge=0, description="Working-resolution ceiling: longer image sides are area-resampled down to it "
                                "at load; a job's max_image_side may ask less, not more (0: full resolution).")
    default_image_side: int = Field(
        DEFAULT_IMAGE_SIDE, ge=0, description="Working side of a job that asks none (capped by NEPF_MAX_IMAGE_SIDE; 0: the ceiling). "
                               "A CPU step draws a fixed number of rays, so a larger side only adds load time, memory "
                               "and evaluation cost within a job's budget (docs/SERVICE.md, 'Limits').")
    max_header_bytes: int = Field(
        65536, description="Cap on a request's line and headers together; past it a 431 (0: none).")
    validate_timeout_s: float = Field(300.0, description="Timeout of the dataset validation subprocess.")
    validate_max_memory_mb: int = Field(4096, description="Address-space cap of the validation subprocess (0: none).")
    python_executable: Optional[str] = Field(
        None, description="Interpreter for the validation subprocess (default: the API's own).")

    # --- jobs / queue --------------------------------------------------------------------
    default_preset: Literal["fast", "paper", "tiny"] = Field("fast", description="Preset when the config names none.")
    job_queue: str = Field("default", description="Celery queue new jobs go to (`default` or `gpu`).")
    device: str = Field("auto", description="Device the worker trains on (auto|cpu|cuda|cuda:N|mps).")
    checkpoint_every: Optional[int] = Field(
        None, description="Checkpoint every N steps (passed to the core; None: the preset's value).")
    export_texture_size: Optional[int] = Field(None, description="Baked texture size (None: the core's default).")
    export_mesh_resolution: Optional[int] = Field(None, description="Marching-cubes grid for export (None: core default).")
    export_max_faces: Optional[int] = Field(None, description="Face budget of the exported mesh (None: core default).")
    visibility_timeout_s: int = Field(
        7 * 24 * 3600, description="Redis visibility timeout; must exceed the longest job.")
    max_deliveries: int = Field(3, description="Redelivery cap, counted in the DB; then the job fails.")
    lease_s: float = Field(60.0, description="A running job's lease; a worker renews it every heartbeat_s.")
    heartbeat_s: float = Field(1.0, description="Worker heartbeat: lease, progress write, cancel-flag poll.")
    reconcile_interval_s: float = Field(15.0, description="How often the API re-queues orphaned jobs (0: never).")
    resend_after_s: float = Field(
        120.0, gt=0, description="A queued job no worker claimed this long after its last send is sent again "
                                 "(its message may be lost); the wait doubles with each re-send, up to an hour.")
    embedded_poll_s: float = Field(0.1, description="Polling interval of the embedded SQLite broker.")
    embedded_worker: bool = Field(True, description="`nepf serve` without a broker starts a local worker.")
    embedded_worker_nice: int = Field(10, description="Nice increment of the embedded worker (keeps the API responsive).")
    pipeline: str = Field(
        "nepf_core.pipeline:run_pipeline", pattern=r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$",
        description="package.module:function the worker runs a job with: "
                    "pipeline(JobRequest) -> summary dict (nepf_core/pipeline.py).")

    # --- HTTP ----------------------------------------------------------------------------
    public_url: Optional[str] = Field(None, description="Base URL printed in the login link.")
    web_dir: Optional[Path] = Field(None, description="Static viewer folder; default web/dist in the repo.")
    cors_origins: str = Field("", description="Comma-separated CORS origins (empty: no CORS).")
    ticket_ttl_s: int = Field(300, description="Lifetime of an SSE ticket.")
    poll_cache_s: float = Field(0.25, description="GET /jobs/{id} micro-cache per API process (0: off).")
    auth_cache_s: float = Field(5.0, description="How long a verified token is cached in the API process.")

    # ---- derived ------------------------------------------------------------------------
    @property
    def data_path(self) -> Path:
        return Path(self.data_dir).expanduser().resolve()

    @property
    def db_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.data_path / 'nepf.sqlite3'}"

    @property
    def embedded(self) -> bool:
        return not self.broker_url

    @property
    def embedded_broker_path(self) -> Path:
        """The SQLite file of the embedded broker (used when ``broker_url`` is unset)."""
        return self.data_path / "broker.sqlite3"

    @property
    def effective_broker_url(self) -> str:
        if self.broker_url:
            return self.broker_url
        return f"nepfsqla+sqlite:///{self.embedded_broker_path}"

    def job_max_side(self, asked: Optional[int]) -> int:
        """The long side a job trains at: its ``max_image_side`` capped by the ceiling
        ``max_image_side``; when it asks nothing, ``default_image_side`` capped the same way (the
        ceiling when that is 0). 0: full size."""
        ceiling = self.max_image_side
        want = int(asked) if asked else self.default_image_side
        if not want:
            return ceiling
        return min(want, ceiling) if ceiling else want

    @property
    def jobs_path(self) -> Path:
        return self.data_path / "jobs"

    @property
    def uploads_path(self) -> Path:
        return self.data_path / "uploads"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    return Settings()


def reset_settings_cache() -> None:
    get_settings.cache_clear()
