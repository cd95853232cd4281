"""``RUN/manifest.json``: every artifact of a run folder with kind, size and SHA-256.

Classification (first match wins, paths relative to the run folder, posix):

| rule | kind |
|---|---|
| ``*.glb`` / ``*.gltf`` | ``glb`` |
| ``*.ply`` / ``*.obj`` | ``mesh`` |
| ``textures/**`` | ``texture`` |
| ``light_field.json`` / ``light_field.bin`` | ``light_field`` |
| ``lights.json`` | ``lights`` |
| ``previews/**.png``, ``previews/relit_canonical.json`` | ``preview`` |
| ``metrics.jsonl``, ``eval.json`` | ``metrics`` |
| ``report.json``, ``summary.json`` (run_job), ``error_vs_time.txt`` (plot failure note) | ``report`` |
| ``config.json``, ``frame.json`` (the GLB's frame) | ``config`` |
| other top-level ``*.png`` / ``*.svg`` / ``*.pdf`` (e.g. ``error_vs_time.png``) | ``plot`` |

Not listed: ``manifest.json`` itself, ``checkpoints/**`` and ``*.pt`` (large, internal),
``progress.json`` (transient status, rewritten while running), temporary files
(``*.tmp``, ``*.part``, names starting with ``.``), and anything matching no rule.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path, PurePosixPath

__all__ = ["artifact_kind", "manifest_entry", "write_manifest", "ARTIFACT_KINDS"]

ARTIFACT_KINDS = ("glb", "mesh", "texture", "light_field", "lights", "preview", "metrics",
                  "report", "config", "plot")

_EXCLUDED_NAMES = {"manifest.json", "progress.json"}


def artifact_kind(rel: str) -> str | None:
    """Kind of the artifact at posix path ``rel`` (relative to the run folder), or None."""
    p = PurePosixPath(rel)
    name, suffix, parts = p.name, p.suffix.lower(), p.parts
    if any(part.startswith(".") for part in parts) or suffix in (".tmp", ".part", ".pt"):
        return None
    if parts[0] == "checkpoints" or name in _EXCLUDED_NAMES and len(parts) == 1:
        return None
    if suffix in (".glb", ".gltf"):
        return "glb"
    if suffix in (".ply", ".obj"):
        return "mesh"
    if parts[0] == "textures" and len(parts) > 1:
        return "texture"
    if len(parts) == 1 and name in ("light_field.json", "light_field.bin"):
        return "light_field"
    if len(parts) == 1 and name == "lights.json":
        return "lights"
    if parts[0] == "previews" and (suffix == ".png" or name == "relit_canonical.json"):
        return "preview"
    if len(parts) == 1 and name in ("metrics.jsonl", "eval.json"):
        return "metrics"
    if len(parts) == 1 and name in ("report.json", "summary.json", "error_vs_time.txt"):
        return "report"
    if len(parts) == 1 and name in ("config.json", "frame.json"):
        return "config"
    if len(parts) == 1 and suffix in (".png", ".svg", ".pdf"):
        return "plot"
    return None


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def manifest_entry(run_dir: str | Path, path: str | Path, kind: str | None = None) -> dict:
    """``{"kind", "path", "bytes", "sha256"}`` for one file (path relative, posix)."""
    run_dir = Path(run_dir)
    path = Path(path)
    if not path.is_absolute():
        path = run_dir / path
    rel = path.resolve().relative_to(run_dir.resolve()).as_posix()
    kind = kind or artifact_kind(rel)
    if kind is None:
        raise ValueError(f"{rel} is not an artifact")
    return {"kind": kind, "path": rel, "bytes": path.stat().st_size, "sha256": _sha256(path)}


def write_manifest(run_dir: str | Path) -> dict:
    """Scan ``run_dir`` and write ``run_dir/manifest.json`` atomically.

    Returns ``{"artifacts": [{"kind", "path", "bytes", "sha256"}, ...]}`` sorted by path, plus
    ``relit_previews`` (the lights and camera of the canonical relit previews) when the folder has
    ``previews/relit_canonical.json``, and ``frame`` (the world's up axis and the rotation
    ``gltf_from_world`` into the GLB's +Y-up frame, :mod:`nepf_core.up_axis`) when it has
    ``frame.json``.
    """
    run_dir = Path(run_dir)
    entries = []
    for root, dirs, files in os.walk(run_dir):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            full = Path(root) / name
            if not full.is_file() or full.is_symlink():
                continue
            rel = full.relative_to(run_dir).as_posix()
            kind = artifact_kind(rel)
            if kind is not None:
                entries.append(manifest_entry(run_dir, full, kind))
    entries.sort(key=lambda e: e["path"])
    manifest = {"artifacts": entries}
    relit = run_dir / "previews" / "relit_canonical.json"
    if relit.is_file():  # the canonical relit previews' lights and camera (nepf_core/relight/previews.py)
        manifest["relit_previews"] = json.loads(relit.read_text())
    frame = run_dir / "frame.json"
    if frame.is_file():  # the GLB's frame (export_asset): the viewer's up axis follows from it
        manifest["frame"] = json.loads(frame.read_text())
    out = run_dir / "manifest.json"
    tmp = run_dir / ".manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2))
    tmp.replace(out)
    return manifest
