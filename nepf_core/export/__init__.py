"""Export a fitted model to a textured asset: mesh, UV atlas, baked PBR textures, GLB,
light field, previews and the run manifest.

Entry points: :func:`export_asset` (writes the artifacts, returns their manifest entries)
and :func:`write_manifest` (scans a run folder, writes ``RUN/manifest.json``). Export only
sees a :class:`FieldQuery` (docs/ARCHITECTURE.md, "The field query protocol").

Pipeline (normalised frame until the last step): chunked narrow-band SDF grid -> marching
cubes at 0
-> drop floaters -> quadric decimation to ``max_faces`` -> field normals at vertices ->
xatlas unwrap -> texel rasterisation -> material queries -> push-pull padding -> PNGs ->
world transform (``world_from_norm``) -> PLY (world) and GLB (rotated to glTF's +Y up,
``nepf_core.up_axis``); light field and fitted lights (written in the GLB's frame); previews
in a VTK subprocess (world frame, orbiting the world's up).

Measured on the development machine (2 CPU cores, no GPU, torch CPU) while other jobs
kept its load average at 8-12, so wall times are inflated; process CPU time
(all threads of the exporting process, not the preview child) is the steadier number.
Input: the analytic sphere FieldQuery of ``tests/export_fixtures.py`` (radius 0.6),
``mesh_resolution=256`` (220,636 marching-cubes faces), ``max_faces=50_000``, 8 turntable
frames + relit at 256², EGL (llvmpipe) previews; one ``export_asset`` call each::

    texture  faces   vertices*  asset.glb              wall     CPU (parent)  SDF grid
    1024²    50,000  31,001     1,869,700 B (1.78 MiB)  61.3 s   23.5 s        narrow band
    1024²    50,000  31,001     1,869,700 B (1.78 MiB)  74.0 s   22.7 s        dense
    1024²    50,000  31,001     1,869,680 B (1.78 MiB)  85.4 s   25.3 s        dense
    2048²    50,000  31,001     2,233,312 B (2.13 MiB)  105.0 s  (not recorded) dense

    * after splitting vertices along UV seams.

    stages of the 61.3 s run: SDF grid (2.1M of 16.8M points evaluated) + marching cubes
    3.2 s, decimation 0.7 s, normals 0.1 s, xatlas unwrap 47.4 s, bake 5.0 s, GLB 0.3 s,
    light field 0.1 s, previews 4.5 s.
    xatlas alone on the same 50k-face mesh, separate run: 38.5 s wall / 15.7 s CPU with
    ``chart_iterations=0`` (our default), 50.2 s / 17.1 s with xatlas' default 1.

The unwrap dominates (:func:`~nepf_core.export.uv_bake.unwrap_uv`), so the face budget is the
main cost knob.
An analytic field is nearly free to evaluate; with a neural field the SDF grid (block
centres plus near-surface blocks: 2.1M queries for a sphere at R = 256), the vertex normals
and the ~0.6·S² texel material queries add the network's cost.
"""

from __future__ import annotations

import io
import json
import time
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
import torch
from PIL import Image

from nepf_core.up_axis import UpFrame

from .glb import write_glb
from .light_field import emitters_to_world, fit_lights, sample_light_field, write_light_field
from .manifest import manifest_entry, write_manifest
from .mesh import (EmptyMeshError, decimate_mesh, extract_mesh, mesh_to_world,
                   vertex_normals_from_field)
from .previews import render_previews
from .uv_bake import bake_material_textures, unwrap_uv

__all__ = ["FieldQuery", "export_asset", "write_manifest", "EmptyMeshError", "mesh_to_world"]


class FieldQuery(Protocol):
    """Export's view of a model (normalised frame, tensors on the model's device)."""

    def sdf(self, x: torch.Tensor) -> torch.Tensor: ...  # [N,3] -> [N]

    def normal(self, x: torch.Tensor) -> torch.Tensor: ...  # [N,3] -> [N,3] unit

    def material(self, x: torch.Tensor, n: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]: ...  # albedo, rough, metal

    def light(self, x: torch.Tensor, n: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]: ...  # unit dir [N,3], intensity [N]

    # optional: ``emitters() -> (positions [K,3], intensity [K]) | None``, the learned global
    # emitters (normalised frame), written to lights.json as they are


def _png_bytes(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", optimize=False, compress_level=6)
    return buf.getvalue()


def _write_bytes(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    return path


def _write_glb(out_dir: Path, baked, uvm, vw: np.ndarray, nw: np.ndarray, m: np.ndarray, frame: UpFrame,
               texture_size: int) -> np.ndarray:
    """``textures/*.png``, ``asset.glb`` (world mesh rotated into the GLB's +Y-up frame by
    ``frame.rotation``) and ``frame.json``; returns the UV faces in the world's winding (flipped
    under a reflection ``det M < 0``; the rotation, ``det = +1``, keeps it)."""
    rot = frame.rotation
    base_png, orm_png = _png_bytes(baked.base_color), _png_bytes(baked.orm)
    _write_bytes(out_dir / "textures" / "base_color.png", base_png)
    _write_bytes(out_dir / "textures" / "orm.png", orm_png)
    faces_uv = uvm.faces if np.linalg.det(m[:3, :3]) > 0 else uvm.faces[:, ::-1]
    write_glb(out_dir / "asset.glb", vw[uvm.vmapping] @ rot.T, nw[uvm.vmapping] @ rot.T, uvm.uv, faces_uv,
              base_png, orm_png,
              extras={"up": [0.0, 1.0, 0.0], "world_up": frame.world_up, "up_source": frame.source,
                      "gltf_from_world": rot.tolist(), "texture_size": int(texture_size),
                      "faces": int(len(uvm.faces)), "world_from_norm": m.tolist()})
    _write_bytes(out_dir / "frame.json", json.dumps(frame.to_json(), indent=2).encode())
    return faces_uv


ASSET_FILES = ("mesh.ply", "textures/base_color.png", "textures/orm.png", "asset.glb", "light_field.json",
               "lights.json", "frame.json")
"""What :func:`export_asset` always writes, relative to the run folder (previews aside)."""


class _StageTimer:
    """Wall seconds of each export stage: :meth:`lap` books the time since the previous lap."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self.t = time.perf_counter()

    def lap(self, name: str) -> None:
        t = time.perf_counter()
        self.timings[name], self.t = t - self.t, t


def _write_mesh(query, m: np.ndarray, out_dir: Path, resolution: int, bbox, max_faces: int, chunk: int, device,
                log, timer: _StageTimer):
    """Marching cubes of the SDF, decimation to ``max_faces``, vertex normals from the field, and
    ``mesh.ply`` in world coordinates (winding flipped under a reflection). Returns ``(mesh
    (normalised frame), normals [V, 3], world vertices [V, 3], world normals [V, 3])``."""
    mesh = extract_mesh(query.sdf, resolution, bbox, chunk=max(chunk, 262144), device=device)
    n_mc = len(mesh.faces)
    timer.lap("marching_cubes")
    mesh = decimate_mesh(mesh, max_faces)
    timer.lap("decimate")
    log(f"export: marching cubes {n_mc} faces -> {len(mesh.faces)} after decimation (budget {max_faces})")
    vn = vertex_normals_from_field(query.normal, np.asarray(mesh.vertices, np.float32), chunk=chunk,
                                   device=device, fallback=np.asarray(mesh.vertex_normals))
    timer.lap("normals")
    vw, nw = mesh_to_world(mesh.vertices, m, vn)
    import trimesh  # local: keeps the module import light for the CLI

    ply = trimesh.Trimesh(vertices=vw, faces=mesh.faces, vertex_normals=nw, process=False)
    if np.linalg.det(m[:3, :3]) < 0:  # a reflection flips the winding
        ply.invert()
    _write_bytes(out_dir / "mesh.ply", ply.export(file_type="ply", vertex_normal=True))
    timer.lap("ply")
    return mesh, vn, vw, nw


def _write_lights(query, mesh, m: np.ndarray, out_dir: Path, rot: np.ndarray, light_samples: int, chunk: int,
                  device) -> dict:
    """Sample the light field on the mesh, fit the lights (object radius in world units) and write
    ``light_field.json`` / ``lights.json`` in the GLB's frame; returns the fitted lights."""
    field = sample_light_field(query.light, query.normal, mesh, m, count=light_samples, chunk=chunk, device=device)
    scale = float(np.cbrt(abs(np.linalg.det(m[:3, :3]))))
    radius_w = float(np.linalg.norm(mesh.vertices - mesh.vertices.mean(0), axis=-1).max()) * scale
    lights = fit_lights(field["points"], field["directions"], field["intensity"], object_radius=radius_w)
    learned = query.emitters() if hasattr(query, "emitters") else None
    if learned is not None:
        lights["emitters"] = emitters_to_world(*learned, m)
    write_light_field(out_dir, field, lights, gltf_from_world=rot)
    return lights


def _relit_previews(query, m: np.ndarray, out_dir: Path, vw: np.ndarray, up, size: int, bsdf_kind: str, device,
                    log) -> list:
    """The three canonical relit previews (:mod:`nepf_core.relight.previews`) around the world
    mesh ``vw``'s bounding-box centre; a failure is logged and leaves none (previews never cost
    the export)."""
    try:
        from nepf_core.relight.previews import write_relit_previews
        centre = 0.5 * (vw.min(0) + vw.max(0))
        return write_relit_previews(query, m, out_dir, centre, float(np.linalg.norm(vw - centre, axis=-1).max()),
                                    up=up, size=size, bsdf_kind=bsdf_kind, device=device)
    except Exception as e:  # noqa: BLE001 -- previews never cost the export
        log(f"warning: relit previews failed (export continues without them): {type(e).__name__}: {e}")
        return []


def _unwrap_and_bake(query, mesh, vn: np.ndarray, texture_size: int, chunk: int, device, timer: _StageTimer):
    """The UV atlas of ``mesh`` (split along seams) and the material baked into its textures."""
    uvm = unwrap_uv(mesh.vertices, mesh.faces, texture_size)
    timer.lap("unwrap")
    pos = np.asarray(mesh.vertices, np.float32)[uvm.vmapping]
    baked = bake_material_textures(query.material, pos, vn[uvm.vmapping], uvm.uv, uvm.faces, texture_size,
                                   chunk=chunk, device=device)
    timer.lap("bake")
    return uvm, baked


def _log_summary(log, timings: dict, out_dir: Path, uvm, texture_size: int, lights: dict) -> None:
    glb_mb = (out_dir / "asset.glb").stat().st_size / 2**20
    log("export: " + ", ".join(f"{k} {v:.2f}s" for k, v in timings.items())
        + f"; asset.glb {glb_mb:.2f} MiB, {len(uvm.faces)} faces, {len(uvm.vmapping)} vertices, "
        f"texture {texture_size}², light: {lights['type']}")


def export_asset(
    query: FieldQuery,
    world_from_norm: np.ndarray,
    out_dir: str | Path,
    *,
    texture_size: int = 1024,
    max_faces: int = 100_000,
    mesh_resolution: int = 256,
    bbox: tuple[float, float] = (-1.0, 1.0),
    device: torch.device | str | None = None,
    log: Callable[[str], None] = print,
    light_samples: int = 4096,
    previews: bool = True,
    preview_frames: int = 8,
    preview_size: int = 256,
    frame: UpFrame | None = None,
    chunk: int = 65536,
    manifest: bool = True,
    relit_bsdf: str = "paper",
) -> list[dict]:
    """Export the asset of a fitted model into ``out_dir`` (the run folder).

    Writes ``mesh.ply`` (world), ``textures/base_color.png`` (sRGB), ``textures/orm.png``
    (linear; R = occlusion = 1, G = roughness, B = metallic), ``asset.glb``,
    ``light_field.json`` and ``lights.json`` (the GLB's +Y-up frame ``x_glb = R x_world``, see
    :mod:`nepf_core.up_axis`), ``frame.json`` (the up axis and ``R``) and, unless
    ``previews=False`` or rendering fails (logged as a warning), ``previews/*.png``, including the
    canonical relit previews ``previews/relit_canonical_K.png`` and their record
    ``previews/relit_canonical.json`` (:mod:`nepf_core.relight.previews`, BSDF ``relit_bsdf``).
    With ``manifest=True`` it then writes ``manifest.json`` for the whole folder.

    Args:
        query: a FieldQuery (normalised frame).
        world_from_norm: ``[4,4]``, ``x_world = M @ [x_norm, 1]``.
        texture_size: S, textures are ``S x S``.
        max_faces: face budget after quadric decimation.
        mesh_resolution: marching-cubes grid points per axis over ``bbox``.
        device: where query tensors live (default: ``query.device`` if present, else CPU).
        frame: the world's up axis (:class:`~nepf_core.up_axis.UpFrame`; None: +z, "default"):
            the GLB is rotated by its ``R`` so that it is +Y up; the previews orbit about it.

    Returns:
        manifest entries ``{"kind", "path", "bytes", "sha256"}`` of the files written here.

    Raises:
        EmptyMeshError: the SDF has no zero crossing in ``bbox``.
    """
    out_dir = Path(out_dir).resolve()  # written paths below must not be re-joined to a relative run dir
    out_dir.mkdir(parents=True, exist_ok=True)
    if device is None:
        device = getattr(query, "device", None) or "cpu"
    m = np.asarray(world_from_norm, dtype=np.float64)
    frame = frame or UpFrame()
    rot, up = frame.rotation, tuple(float(c) for c in frame.up_vector)
    t_all, cpu_all = time.perf_counter(), time.process_time()
    timer = _StageTimer()
    mesh, vn, vw, nw = _write_mesh(query, m, out_dir, mesh_resolution, bbox, max_faces, chunk, device, log, timer)

    uvm, baked = _unwrap_and_bake(query, mesh, vn, texture_size, chunk, device, timer)
    faces_uv = _write_glb(out_dir, baked, uvm, vw, nw, m, frame, texture_size)
    timer.lap("glb")

    lights = _write_lights(query, mesh, m, out_dir, rot, light_samples, chunk, device)
    timer.lap("light_field")

    written = [out_dir / name for name in ASSET_FILES]
    if previews:
        written += render_previews(vw[uvm.vmapping], faces_uv, uvm.uv, nw[uvm.vmapping],
                                   out_dir / "textures" / "base_color.png", out_dir, lights,
                                   frames=preview_frames, size=preview_size, up=up, log=log)
        timer.lap("previews")
        written += _relit_previews(query, m, out_dir, vw, up, preview_size, relit_bsdf, device, log)
        timer.lap("relit_previews")
    timer.timings["total"] = time.perf_counter() - t_all
    timer.timings["cpu_total"] = time.process_time() - cpu_all  # this process only, all threads
    _log_summary(log, timer.timings, out_dir, uvm, texture_size, lights)
    entries = [manifest_entry(out_dir, p) for p in written]
    if manifest:
        write_manifest(out_dir)
    return entries
