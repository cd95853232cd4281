"""Validate an uploaded dataset without importing torch.

``python -m nepf_core.data.validate [--max-side PX] [--max-total-pixels N] DIR`` prints one
JSON line and exits 0 when the dataset loads::

    {"ok": true, "format": "dtu", "n_views": 49, "width": 1600, "height": 1200,
     "working_width": 1600, "working_height": 1200, "has_masks": true,
     "splits": {"train": 49}, "total_pixels": 94080000, "root": "sub/folder",
     "holdout_default_every": 8, "holdout_max_every": 24}

or exits 2 with ``{"ok": false, "errors": [DatasetError.to_dict(), ...]}`` (malformed input, each
error with its own code), or 3 on a bug (``internal_error``, the traceback on stderr only).

Everything a loader would reject is checked: the layout, the metadata, every camera, that
every referenced file lies inside the folder (``paths.py``), the decoded-pixel budget of
all splits together from the image headers (``budget.py``, before any decoding), and every
image and mask decoded one at a time and brought to the working resolution ``max_side``
(nothing is kept, so memory stays at one view). Structural errors stop the check;
per-view errors are collected (at most :data:`MAX_ERRORS`). ``n_views``/``width``/
``height`` (full size) and ``working_width``/``working_height`` (the size a job trains
at) describe the training split; ``holdout_default_every`` / ``holdout_max_every`` are the
default and the largest ``holdout_every`` for it (``split.py``). No message carries the folder's absolute path.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import traceback
from pathlib import Path

from nepf_core.data.errors import DatasetError

MAX_ERRORS = 20
#: exit status of a validator bug (2: the dataset is invalid); the API answers it with a 500
EXIT_INTERNAL_ERROR = 3
INTERNAL_ERROR_MESSAGE = "the dataset validator failed on an internal error (logged on the server)"


def _split_specs(fmt: str, folder: Path) -> dict[str, list]:
    """Per split, the parsed :class:`ViewSpec` list (raises on structural errors)."""
    if fmt == "dtu":
        from nepf_core.data.dtu import parse_dtu
        return {"train": parse_dtu(folder)[0]}
    from nepf_core.data.blender import SPLITS, parse_transforms, split_file
    if fmt == "blender":
        return {s: parse_transforms(split_file(folder, s), folder)
                for s in SPLITS if split_file(folder, s).is_file()}
    if fmt == "colmap":
        from nepf_core.data.colmap import parse_colmap
        return {"train": parse_colmap(folder)[0]}
    from nepf_core.data.ingp import TRANSFORMS
    if fmt == "nerfstudio":
        from nepf_core.data.nerfstudio import nerfstudio_extras
        nerfstudio_extras(folder)   # applied_transform and ply_file_path are checked too
    return {"train": parse_transforms(folder / TRANSFORMS, folder)}


def validate_dataset(root: str | Path, *, max_side: int | None = None,
                     max_total_pixels: int | None = None) -> dict:
    """Check a dataset folder; returns the JSON-ready result described in the module docstring.

    ``max_side``: the working resolution a job would load at (0/None: full size);
    ``max_total_pixels``: the decoded-pixel budget of all splits together (None: none).
    """
    from nepf_core.data.budget import check_total_pixels
    from nepf_core.data.detect import resolve_dataset
    from nepf_core.data.resample import grid_scale
    from nepf_core.data.split import holdout_limits
    from nepf_core.data.views import check_max_side, check_same_alpha, check_same_size, read_view

    errors: list[dict] = []
    try:
        max_side = check_max_side(max_side)
        fmt, folder = resolve_dataset(root)
        splits = _split_specs(fmt, folder)
        images = list(dict.fromkeys(s.image for specs in splits.values() for s in specs))
        total_pixels = check_total_pixels(images, max_total_pixels)
    except DatasetError as e:
        return {"ok": False, "errors": [e.to_dict()]}
    summary = {}
    for name, specs in splits.items():
        first = None
        has_masks = None
        for i, s in enumerate(specs):
            try:
                _, mask, wh, has_alpha = read_view(s, i, max_side=max_side, alpha_mask=fmt != "dtu",
                                                   same_as=first and first[0])
                if first is None:
                    first = (wh, has_alpha)
                check_same_size(wh, first[0], s.label, i)
                if fmt != "dtu":
                    check_same_alpha(has_alpha, first[1], s.label, i)
                has_masks = mask is not None
            except DatasetError as e:
                errors.append(e.to_dict())
                if len(errors) >= MAX_ERRORS:
                    break
        if first is not None:
            (ww, wh_), _ = grid_scale(*first[0], 1, max_side)
            summary[name] = {"n_views": len(specs), "width": first[0][0], "height": first[0][1],
                             "working_width": ww, "working_height": wh_, "has_masks": bool(has_masks)}
        if len(errors) >= MAX_ERRORS:
            break
    if errors:
        return {"ok": False, "errors": errors}
    main = summary.get("train") or next(iter(summary.values()))
    rel_root = Path(folder).resolve().relative_to(Path(root).resolve()).as_posix()
    return {"ok": True, "format": fmt, **main, "splits": {k: v["n_views"] for k, v in summary.items()},
            "total_pixels": total_pixels, "root": rel_root, **holdout_limits(main["n_views"])}


def scrub_paths(result: dict, root: str | Path) -> dict:
    """``result`` with the dataset folder's absolute path (as given and resolved) replaced by
    ``<dataset>`` in every error message and file: a message from deep inside a library
    (an ``OSError``) must not reveal where the server keeps uploads."""
    spellings = sorted({os.path.abspath(root), str(Path(root).resolve())}, key=len, reverse=True)
    for err in result.get("errors") or []:
        for key in ("message", "file"):
            if isinstance(err.get(key), str):
                for s in spellings:
                    err[key] = err[key].replace(s, "<dataset>")
    return result


def main(argv: list[str] | None = None) -> int:
    """CLI: print the JSON result of :func:`validate_dataset`; exit 0 (ok), 2 (invalid) or 3 (a bug)."""
    ap = argparse.ArgumentParser(prog="python -m nepf_core.data.validate")
    ap.add_argument("dir")
    ap.add_argument("--max-side", type=int, default=0, help="working resolution (0: full size)")
    ap.add_argument("--max-total-pixels", type=int, default=None, help="decoded-pixel budget")
    try:
        a = ap.parse_args(sys.argv[1:] if argv is None else argv)
    except SystemExit:
        return 64
    try:
        result = validate_dataset(a.dir, max_side=a.max_side, max_total_pixels=a.max_total_pixels)
    except MemoryError:   # under the API's address-space cap (NEPF_VALIDATE_MAX_MEMORY_MB)
        result = {"ok": False, "errors": [{"code": "dataset_too_large", "file": None, "view": None,
                                           "message": "validating the dataset needed more memory than allowed"}]}
    except Exception:  # noqa: BLE001 - a bug: the traceback to stderr (the server's log), no Python text in the answer
        traceback.print_exc(file=sys.stderr)
        print(json.dumps({"ok": False, "errors": [{"code": "internal_error", "file": None, "view": None,
                                                   "message": INTERNAL_ERROR_MESSAGE}]}))
        return EXIT_INTERNAL_ERROR
    print(json.dumps(scrub_paths(result, a.dir)))
    return 0 if result["ok"] else 2


if __name__ == "__main__":
    sys.exit(main())
