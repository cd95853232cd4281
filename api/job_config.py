"""A job's config (the multipart ``config`` part): one pydantic model, :class:`JobConfig`, that
validates it, documents it (OpenAPI, ``GET /schemas/job-config``) and gives the viewer's form its
limits (``web/src/views/upload.js`` reads that schema). Every error is a 422 ``invalid_config``
naming the key, the allowed values (read from the model's own constraints) and why.

Keys (all optional): ``preset``, ``iters``, ``time_budget_s``, ``name``, ``max_image_side``,
``holdout_every``, ``texture_size``, ``max_faces``, ``up_axis`` (docs/SERVICE.md, "Job options").
:func:`parse_config` checks what needs no dataset; :func:`resolve_holdout_every` the rest once
the validator has counted the views. Nothing here imports ``nepf_core``; the JSON is parsed by
:mod:`nepf_json` (depth, number and string length bounded, duplicate keys refused), the one
parser the dataset loaders use too.
"""

from __future__ import annotations

import json
from typing import Any, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator

from nepf_json import DEFAULT_LIMITS, JsonInputError
from nepf_json import loads as bounded_json_loads

from jobstore.settings import Settings

from .errors import ApiError

PRESETS = ("fast", "paper", "tiny")
#: the baked texture sizes the exporter offers (``nepf fit --texture-size``)
TEXTURE_SIZES = (256, 512, 1024, 2048)
#: bounds of a job's ``max_faces``: below 1,000 faces a decimated mesh loses the shape of most
#: objects; above 2,000,000 the GLB passes ~60 MB (1M vertices with normals and UVs, 2M triangles) and
#: browsers struggle to show it
MAX_FACES_RANGE = (1_000, 2_000_000)
#: a job's ``up_axis``: the input world's axis that the export turns into glTF's +Y; "auto" (or no
#: key): the mean of the cameras' up vectors, snapped to the nearest axis. The same choices as
#: ``nepf fit --up`` (``nepf_core.up_axis.UP_CHOICES``; tests/test_api_job_options.py checks both)
UP_AXIS_CHOICES = ("auto", "+x", "-x", "+y", "-y", "+z", "-z")
#: smallest working side a job may ask for (the loader needs 8 pixels on the short side)
MIN_IMAGE_SIDE = 8
ITERS_RANGE = (1, 10_000_000)
MAX_TIME_BUDGET_S = 30 * 24 * 3600
MAX_NAME = 200

HOLDOUT_RULE = ("0 (train on all views) or an integer >= 2 that holds out views 0, N, 2N, ... "
                "(1 would hold out every view)")
UP_AXIS_RULE = "the input world's up axis, which the GLB turns into glTF's +Y"


class JobConfig(BaseModel):
    """A job's options. In a request every key is optional; a job shows the values in effect."""

    model_config = ConfigDict(extra="forbid")

    preset: Literal["fast", "paper", "tiny"] = Field(
        "fast", description="The training configuration (default: NEPF_DEFAULT_PRESET).")
    iters: Optional[int] = Field(None, ge=ITERS_RANGE[0], le=ITERS_RANGE[1],
                                 description="Training steps (default: the preset's).")
    time_budget_s: Optional[float] = Field(
        None, gt=0, le=MAX_TIME_BUDGET_S, allow_inf_nan=False,
        description="Training wall-clock budget; the schedule is compressed to fit.")
    name: Optional[str] = Field(None, max_length=MAX_NAME, description="Shown in the job list (printable).")
    max_image_side: Optional[int] = Field(
        None, ge=MIN_IMAGE_SIDE, description="Working resolution: longer image sides are area-resampled down to "
                                             "it at load (at most NEPF_MAX_IMAGE_SIDE; None: the server's default).")
    holdout_every: Optional[int] = Field(
        None, ge=0, description="Views 0, N, 2N, ... are held out of training and evaluated on a wall-clock "
                                "schedule (the error-against-time chart). 0: train on all views; otherwise "
                                "2..n_views/2 (at least two held out, at least every other view training). "
                                "Default: 8 for 16 or more views, else 0; the job shows the value used.")
    texture_size: Optional[Literal[256, 512, 1024, 2048]] = Field(
        None, description="Baked texture size of the export (None: NEPF_EXPORT_TEXTURE_SIZE, else the preset's).")
    max_faces: Optional[int] = Field(
        None, ge=MAX_FACES_RANGE[0], le=MAX_FACES_RANGE[1],
        description="Face budget of the exported mesh (None: NEPF_EXPORT_MAX_FACES, else the preset's).")
    up_axis: Optional[str] = Field(
        None, json_schema_extra={"enum": list(UP_AXIS_CHOICES) + [None]},
        description="The input world's up axis, which the export turns into glTF's +Y (the GLB, lights.json "
                    "and light_field.json; the manifest's frame records it). The request may say \"auto\" "
                    "(or nothing; case and a missing + are forgiven): the mean of the cameras' up vectors, "
                    "snapped to the nearest axis; the job then shows None.")

    @field_validator("name")
    @classmethod
    def _printable(cls, v: Optional[str]) -> Optional[str]:
        if v is not None and not v.isprintable():
            raise ValueError("not printable")
        return v

    @field_validator("holdout_every")
    @classmethod
    def _not_one(cls, v: Optional[int]) -> Optional[int]:
        if v == 1:
            raise ValueError("1 would hold out every view")
        return v

    @field_validator("up_axis", mode="before")
    @classmethod
    def _axis(cls, v: Any) -> Optional[str]:
        if v is None:
            return None
        s = v.strip().lower() if isinstance(v, str) else None
        if s is not None and len(s) == 1:
            s = "+" + s
        if s not in UP_AXIS_CHOICES:
            raise ValueError("unknown axis")
        return None if s == "auto" else s

    @field_validator("max_image_side")
    @classmethod
    def _ceiling(cls, v: Optional[int], info: ValidationInfo) -> Optional[int]:
        ceiling = (info.context or {}).get("max_image_side")
        if v is not None and ceiling and v > ceiling:
            raise ValueError("above the ceiling")
        return v


def job_config_schema(settings: Settings) -> dict:
    """The JSON schema of :class:`JobConfig` with this server's values filled in: the default
    preset, and the ceiling and default of ``max_image_side`` (what the viewer's form checks)."""
    schema = JobConfig.model_json_schema()
    props = schema["properties"]
    props["preset"]["default"] = settings.default_preset
    side = props["max_image_side"]
    if settings.max_image_side:
        side["maximum"] = settings.max_image_side
    side["x-server-default"] = settings.job_max_side(None) or None
    return schema


def _field_bounds(key: str) -> dict:
    """The JSON-schema constraints of one field (its non-null branch)."""
    prop = JobConfig.model_json_schema()["properties"][key]
    for branch in prop.get("anyOf", [prop]):
        if branch.get("type") != "null":
            return {**prop, **branch}
    return prop


def requirement(key: str, settings: Settings) -> str:
    """What ``config.<key>`` must be, in words, from the model's constraints."""
    if key == "holdout_every":
        return HOLDOUT_RULE
    if key == "up_axis":
        return f"one of {', '.join(UP_AXIS_CHOICES)}: {UP_AXIS_RULE}"
    if key == "name":
        return f"a printable string of at most {MAX_NAME} characters"
    b = _field_bounds(key)
    if "enum" in b:
        return "one of " + ", ".join(str(x) for x in b["enum"] if x is not None)
    if key == "max_image_side":
        return f"an integer >= {MIN_IMAGE_SIDE}"
    lo = f"[{b['minimum']}" if "minimum" in b else f"({b['exclusiveMinimum']}"
    kind = "an integer" if b.get("type") == "integer" else "a number"
    return f"{kind} in {lo}, {b['maximum']}]"


def _error_message(exc: ValidationError, cfg: dict, settings: Settings) -> str:
    err = exc.errors()[0]
    key = str(err["loc"][0]) if err["loc"] else ""
    if err["type"] == "extra_forbidden":
        extra = sorted(set(cfg) - set(JobConfig.model_fields))
        return f"unknown config key(s) {extra}; allowed: {sorted(JobConfig.model_fields)}"
    value = cfg.get(key)
    if key == "max_image_side" and err["type"] == "value_error" and "ceiling" in str(err.get("msg")):
        c = settings.max_image_side
        return (f"config.max_image_side = {value} is above this server's ceiling of {c} pixels "
                f"(NEPF_MAX_IMAGE_SIDE); ask for {c} or less")
    return f"config.{key} must be {requirement(key, settings)} (got {json.dumps(value)})"


def parse_config(raw: Optional[bytes], settings: Settings) -> dict:
    """The job config, every key checked by :class:`JobConfig` (strictly: ``"8"`` is not 8, a
    bool is not a number); ``preset`` defaults to ``NEPF_DEFAULT_PRESET``. ``holdout_every``'s
    upper bound and default depend on the view count: :func:`resolve_holdout_every`."""
    cfg: Any = {}
    if raw is not None and raw.strip():
        try:
            cfg = bounded_json_loads(raw, source="'config'", limits=DEFAULT_LIMITS)
        except JsonInputError as exc:
            raise ApiError(422, "invalid_config", str(exc)) from None
        if not isinstance(cfg, dict):
            raise ApiError(422, "invalid_config", "'config' must be a JSON object")
    try:
        model = JobConfig.model_validate({"preset": settings.default_preset, **cfg}, strict=True,
                                         context={"max_image_side": settings.max_image_side})
    except ValidationError as exc:
        raise ApiError(422, "invalid_config", _error_message(exc, cfg, settings)) from None
    out = model.model_dump()
    if out["time_budget_s"] is not None:
        out["time_budget_s"] = float(out["time_budget_s"])
    return out


def resolve_holdout_every(cfg: dict, dataset: dict) -> tuple[dict, dict]:
    """``(cfg, dataset)``: the job config with ``holdout_every`` checked against the validated
    dataset and defaulted, and the dataset summary with ``held_out_views`` / ``training_views``.

    The validator (``nepf_core.data.split.holdout_limits``) reports for the training split of
    ``n`` views the default (8 for ``n >= 16``, else 0) and the largest allowed value ``n // 2``:
    at least two views are held out, and at least every other view trains."""
    n = int(dataset.get("n_views") or 0)
    hi = int(dataset.get("holdout_max_every") or 0)
    every = cfg.get("holdout_every")
    if every is None:
        every = int(dataset.get("holdout_default_every", 0))
    elif every and every > hi:
        bound = (f"use 0 or 2..{hi}" if hi >= 2 else "use 0: at least 4 views are needed to hold any out")
        raise ApiError(422, "invalid_config",
                       f"config.holdout_every = {every} is too large for this dataset's {n} training views: {bound} "
                       "(at least two views held out, at least every other view training)")
    held = -(-n // every) if every else 0
    return ({**cfg, "holdout_every": every},
            {**dataset, "held_out_views": held, "training_views": n - held})
