"""A job's config (the multipart ``config`` part): parsed and checked, every error a 422
``invalid_config`` naming the key, the allowed values and why.

Keys (all optional): ``preset``, ``iters``, ``time_budget_s``, ``name``, ``max_image_side``,
``holdout_every``, ``texture_size``, ``max_faces``, ``up_axis`` (docs/SERVICE.md, "Job options").
:func:`parse_config` checks what needs no dataset; :func:`resolve_holdout_every` the rest once
the validator has counted the views. Nothing here imports ``nepf_core``;
the JSON is parsed by :mod:`nepf_json` (depth, number and string length bounded, duplicate keys
refused), the one parser the dataset loaders use too.
"""

from __future__ import annotations

import json
from typing import Optional

from nepf_json import DEFAULT_LIMITS, JsonInputError
from nepf_json import loads as bounded_json_loads

from .errors import ApiError
from .settings import Settings


def parse_config(raw: Optional[bytes], settings: Settings) -> dict:
    """The job config (every key optional): ``preset``, ``iters``, ``time_budget_s``, ``name``,
    ``max_image_side``, ``holdout_every``, ``texture_size``, ``max_faces``, ``up_axis``.

    ``max_image_side``: the working resolution the job trains at, at most the ceiling
    ``NEPF_MAX_IMAGE_SIDE`` (None: the ceiling). ``holdout_every``: its type and sign here; its
    upper bound and its default depend on the view count, see :func:`resolve_holdout_every`.
    ``texture_size`` / ``max_faces``: the export's sizes, overriding ``NEPF_EXPORT_TEXTURE_SIZE``
    / ``NEPF_EXPORT_MAX_FACES`` (None: those). ``up_axis``: see :func:`check_up_axis`."""
    cfg: dict = {}
    if raw is not None and raw.strip():
        try:
            cfg = bounded_json_loads(raw, source="'config'", limits=DEFAULT_LIMITS)
        except JsonInputError as exc:
            raise ApiError(422, "invalid_config", str(exc)) from None
        if not isinstance(cfg, dict):
            raise ApiError(422, "invalid_config", "'config' must be a JSON object")
    allowed = {"preset", "iters", "time_budget_s", "name", "max_image_side", "holdout_every", "texture_size",
               "max_faces", "up_axis"}
    extra = sorted(set(cfg) - allowed)
    if extra:
        raise ApiError(422, "invalid_config",
                       f"unknown config key(s) {extra}; allowed: {sorted(allowed)}")
    preset = cfg.get("preset", settings.default_preset)
    if preset not in ("fast", "paper", "tiny"):
        raise ApiError(422, "invalid_config", "config.preset must be one of fast, paper, tiny")
    iters = cfg.get("iters")
    if iters is not None and (isinstance(iters, bool) or not isinstance(iters, int)
                              or not 1 <= iters <= 10_000_000):
        raise ApiError(422, "invalid_config", "config.iters must be an integer in [1, 10000000]")
    budget = cfg.get("time_budget_s")
    if budget is not None and (isinstance(budget, bool) or not isinstance(budget, (int, float))
                               or not 0 < float(budget) <= 30 * 24 * 3600 or budget != budget):
        raise ApiError(422, "invalid_config", "config.time_budget_s must be a number in (0, 2592000]")
    name = cfg.get("name")
    if name is not None and (not isinstance(name, str) or len(name) > 200 or not name.isprintable()):
        raise ApiError(422, "invalid_config", "config.name must be a printable string of at most 200 characters")
    return {"preset": preset, "iters": iters,
            "time_budget_s": float(budget) if budget is not None else None, "name": name,
            "max_image_side": check_max_image_side(cfg.get("max_image_side"), settings),
            **check_export_options(cfg), "holdout_every": check_holdout_type(cfg.get("holdout_every")),
            "up_axis": check_up_axis(cfg.get("up_axis"))}


#: the baked texture sizes the exporter offers (``nepf fit --texture-size``)
TEXTURE_SIZES = (256, 512, 1024, 2048)
#: bounds of a job's ``max_faces``: below 1,000 faces a decimated mesh loses the shape of most
#: objects; above 2,000,000 the GLB passes ~60 MB (1M vertices with normals and UVs, 2M triangles) and
#: browsers struggle to show it
MAX_FACES_RANGE = (1_000, 2_000_000)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_export_options(cfg: dict) -> dict:
    """``{"texture_size", "max_faces"}`` of a job config (None when not given)."""
    size, faces = cfg.get("texture_size"), cfg.get("max_faces")
    if size is not None and (not _is_int(size) or size not in TEXTURE_SIZES):
        sizes = ", ".join(map(str, TEXTURE_SIZES))
        raise ApiError(422, "invalid_config", f"config.texture_size must be one of {sizes} (got {json.dumps(size)})")
    lo, hi = MAX_FACES_RANGE
    if faces is not None and (not _is_int(faces) or not lo <= faces <= hi):
        raise ApiError(422, "invalid_config", f"config.max_faces must be an integer in [{lo}, {hi}] "
                                              f"(got {json.dumps(faces)})")
    return {"texture_size": size, "max_faces": faces}


#: a job's ``up_axis``: the input world's axis that the export turns into glTF's +Y; "auto" (or no
#: key): the mean of the cameras' up vectors, snapped to the nearest axis. The same choices as
#: ``nepf fit --up`` (``nepf_core.up_axis.UP_CHOICES``; tests/test_api_job_options.py checks both)
UP_AXIS_CHOICES = ("auto", "+x", "-x", "+y", "-y", "+z", "-z")


def check_up_axis(value) -> Optional[str]:
    """A job's ``up_axis``: ``"+x"`` ... ``"-z"`` (case and a missing ``+`` forgiven), or None
    for ``"auto"`` / no key."""
    if value is None:
        return None
    s = value.strip().lower() if isinstance(value, str) else None
    if s is not None and len(s) == 1:
        s = "+" + s
    if s not in UP_AXIS_CHOICES:
        raise ApiError(422, "invalid_config", f"config.up_axis must be one of {', '.join(UP_AXIS_CHOICES)}: the "
                                              f"input world's up axis, which the GLB turns into glTF's +Y "
                                              f"(got {json.dumps(value)})")
    return None if s == "auto" else s


def check_holdout_type(value) -> Optional[int]:
    """A job's ``holdout_every`` before the dataset is known: None, 0, or an integer >= 2."""
    if value is not None and (not _is_int(value) or value < 0 or value == 1):
        raise ApiError(422, "invalid_config",
                       f"config.holdout_every must be 0 (train on all views) or an integer >= 2 that holds out "
                       f"views 0, N, 2N, ... (got {json.dumps(value)}; 1 would hold out every view)")
    return value


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


#: smallest working side a job may ask for (the loader needs 8 pixels on the short side)
MIN_IMAGE_SIDE = 8


def check_max_image_side(value, settings: Settings) -> Optional[int]:
    """A job's ``max_image_side``: an integer in [8, NEPF_MAX_IMAGE_SIDE] (no upper bound
    when the ceiling is 0), or None."""
    if value is None:
        return None
    ceiling = settings.max_image_side
    if isinstance(value, bool) or not isinstance(value, int) or value < MIN_IMAGE_SIDE:
        raise ApiError(422, "invalid_config", f"config.max_image_side must be an integer >= {MIN_IMAGE_SIDE}")
    if ceiling and value > ceiling:
        raise ApiError(422, "invalid_config",
                       f"config.max_image_side = {value} is above this server's ceiling of {ceiling} "
                       f"pixels (NEPF_MAX_IMAGE_SIDE); ask for {ceiling} or less")
    return value
