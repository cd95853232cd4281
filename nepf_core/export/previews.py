"""Server-side previews of the baked asset (pyvista / VTK off-screen), crash-isolated.

Writes ``previews/turntable_XX.png`` (orbit around the ``up`` axis, textured with the baked
baseColor), ``previews/relit.png`` (one point light moved 120 degrees about ``up`` from the
fitted light of ``lights.json``) and ``previews/thumb.png`` (small copy of frame 0).

VTK runs in a **child process** (``python nepf_core/export/_preview_child.py JOB.json``, run
by file path so the child imports only numpy, Pillow and pyvista, not torch): a VTK or
driver crash (segfault, missing GL library) ends the child, and the caller only logs a
warning. Headless backends are tried in order: ``$VTK_DEFAULT_OPENGL_WINDOW`` when set,
then ``vtkEGLRenderWindow`` (Mesa EGL, software llvmpipe), then
``vtkOSOpenGLRenderWindow`` (OSMesa). On Debian 12 these need the packages in
``.ci/apt-packages.txt``: ``libegl1 libegl-mesa0 libgl1-mesa-dri`` (EGL) and ``libosmesa6``
(OSMesa); no X server.

The child's entry point is a parameter, ``renderer_script`` (default :data:`PREVIEW_CHILD`):
any script with the same contract can stand in, e.g. one that crashes natively, to check that
a crash costs only the previews (``tests/test_export_parts.py``). Contract: run as
``python SCRIPT JOB.json``; print ``{"written": [names in out_dir]}`` as the last stdout line and
exit 0; exit :data:`~nepf_core.export._preview_child.BAD_JOB` (3) for unusable inputs.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from ._preview_child import BAD_JOB as _BAD_JOB

__all__ = ["render_previews", "BACKENDS", "BACKGROUND", "PREVIEW_CHILD"]

PREVIEW_CHILD = Path(__file__).with_name("_preview_child.py")
"""The VTK renderer run in the child process (the default ``renderer_script``)."""

BACKENDS = ("vtkEGLRenderWindow", "vtkOSOpenGLRenderWindow")
"""Headless VTK render windows tried in order (after ``$VTK_DEFAULT_OPENGL_WINDOW``)."""

BACKGROUND = (31, 33, 38)
"""Preview background colour (sRGB 8-bit)."""


def render_previews(
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    normals: np.ndarray,
    base_color_png: str | Path,
    out_dir: str | Path,
    lights: dict | None = None,
    frames: int = 8,
    size: int = 256,
    thumb_size: int = 96,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    timeout_s: float = 240.0,
    log: Callable[[str], None] = print,
    renderer_script: str | Path = PREVIEW_CHILD,
) -> list[Path]:
    """Render previews in a subprocess; returns the written PNG paths ([] on failure).

    Args:
        vertices ``[V,3]`` (world), faces ``[F,3]``, uv ``[V,2]`` (glTF top-left origin),
        normals ``[V,3]``: the exported asset. base_color_png: its sRGB texture.
        out_dir: the run folder (PNGs go to ``out_dir/previews``).
        lights: the ``lights.json`` dict (for the relit view), optional.
        up: world up axis for the orbit (the synthetic scenes are Z-up).
        renderer_script: the child's entry point (see the module docstring for its contract).
    """
    out_dir = Path(out_dir)
    prev_dir = out_dir / "previews"
    prev_dir.mkdir(parents=True, exist_ok=True)
    for stale in [*prev_dir.glob("turntable_*.png"), prev_dir / "relit.png", prev_dir / "thumb.png"]:
        stale.unlink(missing_ok=True)  # a re-export must not list an older export's frames
    with tempfile.TemporaryDirectory(prefix="nepf_preview_") as tmp:
        npz = Path(tmp) / "mesh.npz"
        np.savez(npz, vertices=np.asarray(vertices, np.float32), faces=np.asarray(faces, np.int64),
                 uv=np.asarray(uv, np.float32), normals=np.asarray(normals, np.float32))
        job = {"mesh": str(npz), "texture": str(Path(base_color_png).resolve()),
               "out_dir": str(prev_dir.resolve()), "lights": lights, "frames": int(frames),
               "size": int(size), "thumb_size": int(thumb_size), "up": list(map(float, up)),
               "background": BACKGROUND}
        job_path = Path(tmp) / "job.json"
        job_path.write_text(json.dumps(job))
        backends = list(BACKENDS)
        env_backend = os.environ.get("VTK_DEFAULT_OPENGL_WINDOW")
        if env_backend:
            backends = [env_backend] + [b for b in backends if b != env_backend]
        errors = []
        for backend in backends:
            env = dict(os.environ, VTK_DEFAULT_OPENGL_WINDOW=backend, PYVISTA_OFF_SCREEN="true")
            try:
                proc = subprocess.run([sys.executable, str(renderer_script), str(job_path)],
                                      env=env, capture_output=True, text=True, timeout=timeout_s)
            except subprocess.TimeoutExpired:
                errors.append(f"{backend}: timed out after {timeout_s:.0f} s")
                continue
            if proc.returncode == _BAD_JOB:  # the inputs are wrong: another backend won't help
                errors.append(f"bad preview job: {proc.stderr.strip()[-600:]}")
                break
            if proc.returncode == 0:
                try:
                    names = json.loads(proc.stdout.strip().splitlines()[-1])["written"]
                    return [prev_dir / n for n in names]
                except (ValueError, KeyError, IndexError):
                    errors.append(f"{backend}: unreadable child output {proc.stdout[-300:]!r}")
                    continue
            how = (f"killed by signal {-proc.returncode}" if proc.returncode < 0
                   else f"exit {proc.returncode}")
            errors.append(f"{backend}: {how}: {proc.stderr.strip()[-600:]}")
        log("warning: previews failed on every VTK backend (export continues without them): "
            + " | ".join(errors))
        return []
