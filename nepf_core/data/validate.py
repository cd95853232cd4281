"""Validate an uploaded dataset without importing torch.

``python -m nepf_core.data.validate DIR`` prints one JSON line and exits 0 when the dataset
loads::

    {"ok": true, "format": "dtu", "n_views": 49, "width": 1600, "height": 1200,
     "has_masks": true, "splits": {"train": 49}, "root": "sub/folder"}

or exits 2 with ``{"ok": false, "errors": [DatasetError.to_dict(), ...]}``.

Everything a loader would reject is checked: the layout, the metadata, every camera, and
every image and mask decoded one at a time (nothing is kept, so memory stays at one
view). Structural errors stop the check; per-view errors are collected (at most
:data:`MAX_ERRORS`). ``n_views``/``width``/``height`` describe the training split.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from nepf_core.data.errors import DatasetError

MAX_ERRORS = 20


def _split_specs(fmt: str, folder: Path) -> dict[str, list]:
    """Per split, the parsed :class:`ViewSpec` list (raises on structural errors)."""
    if fmt == "dtu":
        from nepf_core.data.dtu import parse_dtu
        return {"train": parse_dtu(folder)[0]}
    from nepf_core.data.blender import SPLITS, parse_transforms, split_file
    if fmt == "blender":
        return {s: parse_transforms(split_file(folder, s), folder)
                for s in SPLITS if split_file(folder, s).is_file()}
    from nepf_core.data.ingp import TRANSFORMS
    return {"train": parse_transforms(folder / TRANSFORMS, folder)}


def validate_dataset(root: str | Path) -> dict:
    """Check a dataset folder; returns the JSON-ready result described in the module docstring."""
    from nepf_core.data.detect import resolve_dataset
    from nepf_core.data.images import check_same_alpha, check_same_size, read_view

    errors: list[dict] = []
    try:
        fmt, folder = resolve_dataset(root)
        splits = _split_specs(fmt, folder)
    except DatasetError as e:
        return {"ok": False, "errors": [e.to_dict()]}
    summary = {}
    for name, specs in splits.items():
        first = None
        has_masks = None
        for i, s in enumerate(specs):
            try:
                _, mask, wh, has_alpha = read_view(s, i, alpha_mask=fmt != "dtu",
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
            summary[name] = {"n_views": len(specs), "width": first[0][0], "height": first[0][1],
                             "has_masks": bool(has_masks)}
        if len(errors) >= MAX_ERRORS:
            break
    if errors:
        return {"ok": False, "errors": errors}
    main = summary.get("train") or next(iter(summary.values()))
    rel_root = Path(folder).resolve().relative_to(Path(root).resolve()).as_posix()
    return {"ok": True, "format": fmt, **main,
            "splits": {k: v["n_views"] for k, v in summary.items()}, "root": rel_root}


def main(argv: list[str] | None = None) -> int:
    """CLI: print the JSON result of :func:`validate_dataset`; exit 0 (ok) or 2 (invalid)."""
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m nepf_core.data.validate DIR", file=sys.stderr)
        return 64
    try:
        result = validate_dataset(argv[0])
    except Exception as e:  # a bug must still answer in JSON, never with a traceback
        result = {"ok": False, "errors": [{"code": "internal_error", "message": f"{type(e).__name__}: {e}",
                                           "file": None, "view": None}]}
    print(json.dumps(result))
    return 0 if result["ok"] else 2


if __name__ == "__main__":
    sys.exit(main())
