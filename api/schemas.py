"""Pydantic schemas by role (``JobPublic`` out, the multipart form in)."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal, Optional

from pydantic import BaseModel, Field

from .job_config import JobConfig  # the one model of a job's options (validation, docs, the form)

Status = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class Progress(BaseModel):
    step: int = 0
    total: Optional[int] = None
    fraction: float = 0.0
    stage: Optional[str] = None
    eta_s: Optional[float] = None
    wall_s: Optional[float] = None


class Delivery(BaseModel):
    attempts: int = Field(0, description="How many times a worker claimed the job (redeliveries + 1).")
    attempt_log: list[dict[str, Any]] = Field(default_factory=list,
                                              description="Per claim: worker, claimed_at, first_step seen.")
    completions: int = Field(0, description="Final results recorded (0 or 1).")
    sends: int = Field(0, description="Times the job was sent to the broker (the reconciler re-sends orphans).")


class JobPublic(BaseModel):
    id: str
    name: Optional[str] = None
    status: Status
    progress: Progress
    created_at: dt.datetime
    started_at: Optional[dt.datetime] = None
    finished_at: Optional[dt.datetime] = None
    error: Optional[str] = None
    config: JobConfig
    dataset: dict[str, Any] = Field(default_factory=dict, description="What the validator found.")
    decisions: Optional[list[dict[str, Any]]] = Field(
        None, description="Adaptivity decisions reported by the core (report.json), once available.")
    cancel_requested: bool = False
    delivery: Delivery
    links: dict[str, str]


class JobList(BaseModel):
    items: list[JobPublic]
    total: int
    limit: int
    offset: int
    next: Optional[str] = None


class MetricsPage(BaseModel):
    records: list[dict[str, Any]] = Field(
        description="metrics.jsonl records: step, wall_s, losses; kind=sync: psnr_r/psnr_surf/psnr_vol; "
                    "kind=test (held-out views): test_psnr (masked where masks exist), test_psnr_full, "
                    "test_psnr_radiance, test_ssim, test_views; with ground truth chamfer, albedo_psnr.")
    since: int = Field(description="The cursor this page starts at.")
    next_since: int = Field(description="Pass as ?since= to get only newer records.")
    status: Status


class Artifact(BaseModel):
    kind: Optional[str] = None
    path: str
    bytes: Optional[int] = None
    sha256: Optional[str] = None
    content_type: str
    url: str


class ArtifactList(BaseModel):
    artifacts: list[Artifact]
    manifest: bool = Field(description="False while the export manifest does not exist yet.")
    status: Status
    frame: Optional[dict[str, Any]] = Field(
        None, description="The manifest's frame: the input world's up axis (world_up, up_source) and the rotation "
                          "gltf_from_world into the GLB's +Y-up frame (x_glb = R x_world); None before the export.")


class Ticket(BaseModel):
    ticket: str
    expires_in: int
    url: str


class ErrorItem(BaseModel):
    code: Optional[str] = None
    message: Optional[str] = None
    file: Optional[str] = None
    view: Optional[int] = None


class ErrorBody(BaseModel):
    detail: str
    code: str
    errors: list[ErrorItem] = Field(default_factory=list)


class Health(BaseModel):
    ok: bool
    checks: dict[str, Any] = Field(default_factory=dict)
