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
    problems = _job_problems(job, v, f)
    if problems:
        print("; ".join(problems), file=sys.stderr)
        return BAD_JOB

    import pyvista as pv
    out = Path(job["out_dir"])
    orbit = _Orbit.around(v, np.asarray(job["up"], dtype=np.float64))
    pl = pv.Plotter(off_screen=True, window_size=(job["size"], job["size"]))
    pl.set_background(np.array(job["background"], dtype=np.float64) / 255.0)
    pl.add_mesh(_textured_mesh(pv, v, f, uv, nrm), texture=pv.read_texture(job["texture"]), smooth_shading=True,
                ambient=0.15, diffuse=0.85, specular=0.2, specular_power=20.0)
    pl.camera.view_angle = 30.0
    written = _turntable(pl, orbit, job["frames"], job["thumb_size"], out)
    moved = _relit_view(pl, pv, orbit, job.get("lights") or {}, out)
    written.append("relit.png")
    pl.close()
    print(json.dumps({"written": written, "light": moved.tolist()}))
    return 0


def _job_problems(job: dict, v: np.ndarray, f: np.ndarray) -> list[str]:
    """What makes the job unusable (checked before VTK is imported)."""
    problems = []
    if not Path(job["texture"]).is_file():
        problems.append(f"texture not found: {job['texture']}")
    if len(f) == 0 or f.min() < 0 or f.max() >= len(v) or not np.isfinite(v).all():
        problems.append("mesh has no faces, bad face indices or non-finite vertices")
    return problems


def _textured_mesh(pv, v: np.ndarray, f: np.ndarray, uv: np.ndarray, nrm: np.ndarray):
    """The mesh as VTK polygons with its normals and texture coordinates (VTK's texture origin is
    bottom-left, glTF's top-left: ``t = 1 - v``)."""
    mesh = pv.PolyData(v.astype(np.float64),
                       np.hstack([np.full((len(f), 1), 3, np.int64), f]).ravel())
    mesh.point_data.active_normals = nrm
    mesh.active_texture_coordinates = np.c_[uv[:, 0], 1.0 - uv[:, 1]].astype(np.float32)
    return mesh


class _Orbit:
    """Cameras on a circle 20 degrees above the mesh's horizon, looking at its bounding box's
    centre from where its bounding sphere fills ~75 % of a 30-degree frame."""

    def __init__(self, centre: np.ndarray, radius: float, up: np.ndarray) -> None:
        self.centre, self.radius = centre, radius
        self.up, self.e1, self.e2 = _orbit_basis(up)
        self.dist = 1.35 * radius / np.sin(np.deg2rad(15.0))
        self.elev = np.deg2rad(20.0)

    @classmethod
    def around(cls, v: np.ndarray, up: np.ndarray) -> "_Orbit":
        centre = 0.5 * (v.min(0) + v.max(0))
        return cls(centre, float(np.linalg.norm(v - centre, axis=-1).max()), up)

    def place(self, pl, az: float) -> None:
        """Put the camera at azimuth ``az`` (radians from ``e1`` towards ``e2``)."""
        d = np.cos(self.elev) * (np.cos(az) * self.e1 + np.sin(az) * self.e2) + np.sin(self.elev) * self.up
        # camera_position (not camera.position) also marks the camera as set, so pyvista
        # does not reset it to its default view on the first render
        pl.camera_position = [tuple(self.centre + self.dist * d), tuple(self.centre), tuple(self.up)]
        pl.camera.clipping_range = (max(self.dist - 2 * self.radius, 1e-3 * self.dist), self.dist + 2 * self.radius)


def _screenshot(pl, path: Path) -> None:
    from PIL import Image
    pl.render()
    img = pl.screenshot(return_img=True)
    Image.fromarray(np.ascontiguousarray(img[..., :3])).save(path)


def _turntable(pl, orbit: _Orbit, frames: int, thumb_size: int, out: Path) -> list[str]:
    """``turntable_KK.png`` at ``frames`` evenly spaced azimuths, and ``thumb.png`` from the first."""
    from PIL import Image
    written = []
    for k in range(frames):
        orbit.place(pl, 2 * np.pi * k / frames)
        name = f"turntable_{k:02d}.png"
        _screenshot(pl, out / name)
        written.append(name)
    if written:
        first = Image.open(out / written[0])
        first.resize((thumb_size, thumb_size), Image.LANCZOS).save(out / "thumb.png")
        written.append("thumb.png")
    return written


def _relit_view(pl, pv, orbit: _Orbit, lights: dict, out: Path) -> np.ndarray:
    """``relit.png``: one point light, moved 120 degrees about ``up`` from the fitted light (its
    position, else 3 radii along its dominant direction); returns the moved light's position."""
    point = (lights.get("point_light") or {}).get("position")
    if point is not None:
        lpos = np.asarray(point, dtype=np.float64)
    else:
        ddir = np.asarray(lights.get("dominant_direction") or (orbit.e1 + orbit.up), dtype=np.float64)
        lpos = orbit.centre + 3.0 * orbit.radius * ddir / np.linalg.norm(ddir)
    moved = orbit.centre + _rotate_about(lpos - orbit.centre, orbit.up, np.deg2rad(120.0))
    pl.remove_all_lights()
    light = pv.Light(position=tuple(moved), focal_point=tuple(orbit.centre), light_type="scene light",
                     intensity=1.0)
    light.positional = True
    light.cone_angle = 180.0
    pl.add_light(light)
    orbit.place(pl, 0.0)
    _screenshot(pl, out / "relit.png")
    return moved


if __name__ == "__main__":  # pragma: no cover - exercised through render_previews
    sys.exit(main(sys.argv[1]))
