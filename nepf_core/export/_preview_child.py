"""Child process of :func:`nepf_core.export.previews.render_previews` (VTK off-screen).

Run as ``python _preview_child.py JOB.json`` (by path: imports only numpy, Pillow, pyvista).
Prints ``{"written": [names]}`` as its last stdout line; exit 3 = unusable inputs.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

BAD_JOB = 3
"""Child exit status for unusable inputs (checked before VTK is imported; not retried)."""


def _orbit_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    up = up / np.linalg.norm(up)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return up, e1, e2


def _rotate_about(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: ``v cos a + (k x v) sin a + k (k.v)(1 - cos a)``."""
    k = axis / np.linalg.norm(axis)
    return v * np.cos(angle) + np.cross(k, v) * np.sin(angle) + k * (k @ v) * (1 - np.cos(angle))


def main(job_path: str) -> int:
    job = json.loads(Path(job_path).read_text())
    data = np.load(job["mesh"])
    v, f, uv, nrm = data["vertices"], data["faces"], data["uv"], data["normals"]
    problems = []
    if not Path(job["texture"]).is_file():
        problems.append(f"texture not found: {job['texture']}")
    if len(f) == 0 or f.min() < 0 or f.max() >= len(v) or not np.isfinite(v).all():
        problems.append("mesh has no faces, bad face indices or non-finite vertices")
    if problems:
        print("; ".join(problems), file=sys.stderr)
        return BAD_JOB

    import pyvista as pv
    from PIL import Image
    size, frames = job["size"], job["frames"]
    out = Path(job["out_dir"])
    bg = np.array(job["background"], dtype=np.float64) / 255.0
    up, e1, e2 = _orbit_basis(np.asarray(job["up"], dtype=np.float64))

    mesh = pv.PolyData(v.astype(np.float64),
                       np.hstack([np.full((len(f), 1), 3, np.int64), f]).ravel())
    mesh.point_data.active_normals = nrm
    # VTK texture origin is bottom-left, glTF's top-left: t = 1 - v.
    mesh.active_texture_coordinates = np.c_[uv[:, 0], 1.0 - uv[:, 1]].astype(np.float32)
    tex = pv.read_texture(job["texture"])

    centre = 0.5 * (v.min(0) + v.max(0))
    radius = float(np.linalg.norm(v - centre, axis=-1).max())
    dist = 1.35 * radius / np.sin(np.deg2rad(15.0))  # bounding sphere fills ~75% of the frame
    elev = np.deg2rad(20.0)

    pl = pv.Plotter(off_screen=True, window_size=(size, size))
    pl.set_background(bg)
    pl.add_mesh(mesh, texture=tex, smooth_shading=True, ambient=0.15, diffuse=0.85, specular=0.2,
                specular_power=20.0)
    pl.camera.view_angle = 30.0
    written = []

    def place(az: float):
        d = np.cos(elev) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(elev) * up
        # camera_position (not camera.position) also marks the camera as set, so pyvista
        # does not reset it to its default view on the first render
        pl.camera_position = [tuple(centre + dist * d), tuple(centre), tuple(up)]
        pl.camera.clipping_range = (max(dist - 2 * radius, 1e-3 * dist), dist + 2 * radius)

    for k in range(frames):
        place(2 * np.pi * k / frames)
        pl.render()
        img = pl.screenshot(return_img=True)
        name = f"turntable_{k:02d}.png"
        Image.fromarray(np.ascontiguousarray(img[..., :3])).save(out / name)
        written.append(name)
    if written:
        first = Image.open(out / written[0])
        first.resize((job["thumb_size"], job["thumb_size"]), Image.LANCZOS).save(out / "thumb.png")
        written.append("thumb.png")

    # relit: one point light, moved 120 degrees about `up` from the fitted light
    lights = job.get("lights") or {}
    point = (lights.get("point_light") or {}).get("position")
    if point is not None:
        lpos = np.asarray(point, dtype=np.float64)
    else:
        ddir = np.asarray(lights.get("dominant_direction") or (e1 + up), dtype=np.float64)
        lpos = centre + 3.0 * radius * ddir / np.linalg.norm(ddir)
    moved = centre + _rotate_about(lpos - centre, up, np.deg2rad(120.0))
    pl.remove_all_lights()
    light = pv.Light(position=tuple(moved), focal_point=tuple(centre), light_type="scene light",
                     intensity=1.0)
    light.positional = True
    light.cone_angle = 180.0
    pl.add_light(light)
    place(0.0)
    pl.render()
    img = pl.screenshot(return_img=True)
    Image.fromarray(np.ascontiguousarray(img[..., :3])).save(out / "relit.png")
    written.append("relit.png")
    pl.close()
    print(json.dumps({"written": written, "light": moved.tolist()}))
    return 0


if __name__ == "__main__":  # pragma: no cover - exercised through render_previews
    sys.exit(main(sys.argv[1]))
