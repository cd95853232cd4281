"""The export's canonical relit previews: the asset under three fixed point lights, from one fixed
camera, so that a viewer can put the same lights and camera on the GLB and compare.

* Lights: :func:`nepf_core.relight.lights.canonical_lights` (3 R from the centre, elevation 45 deg,
  azimuths 0 / 120 / 240 deg about the viewer's up axis, white, irradiance 2 at the centre).
* Camera: looking at the centre from azimuth :data:`CAMERA_AZIMUTH_DEG` and elevation
  :data:`CAMERA_ELEVATION_DEG` (same axes), vertical field of view :data:`CAMERA_FOV_DEG`, at the
  distance where the object's bounding sphere fills :data:`FILL` of the view height.
* Rendering: :func:`nepf_core.relight.render.relight_views` on the FieldQuery (sphere-traced
  surface, shadows through the SDF), ``sRGB(clip(L, 0, 1))`` on black.

Files: ``previews/relit_canonical_K.png`` (K = 0, 1, 2) and ``previews/relit_canonical.json``
(lights and camera in the input's world frame, BSDF kind, image names), which
:func:`nepf_core.export.manifest.write_manifest` copies into the manifest as ``relit_previews``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from nepf_core.relight.lights import CANONICAL_AZIMUTHS_DEG, CANONICAL_ELEVATION_DEG, canonical_lights, horizontal_axes

CAMERA_AZIMUTH_DEG = 30.0
CAMERA_ELEVATION_DEG = 20.0
CAMERA_FOV_DEG = 40.0
FILL = 0.8
"""The bounding sphere's diameter spans this fraction of the image height."""
RECORD = "relit_canonical.json"


def canonical_camera(center_world, radius_world: float, up, size: int) -> dict:
    """The preview camera (module docstring): ``position_world``, ``target_world``, ``up``,
    ``fov_y_deg``, ``width``, ``height``, and ``c2w_world`` (4x4 OpenCV: x right, y down, z forward)."""
    c = np.asarray(center_world, np.float64)
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    ax, ay = horizontal_axes(u)
    az, el = math.radians(CAMERA_AZIMUTH_DEG), math.radians(CAMERA_ELEVATION_DEG)
    half = math.radians(CAMERA_FOV_DEG) / 2
    dist = radius_world / math.sin(half * FILL) if radius_world > 0 else 1.0
    back = math.cos(el) * (math.cos(az) * ax + math.sin(az) * ay) + math.sin(el) * u
    pos = c + dist * back
    fwd = -back
    right = np.cross(fwd, u)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, fwd, pos
    return {"position_world": pos.tolist(), "target_world": c.tolist(), "up": u.tolist(),
            "fov_y_deg": CAMERA_FOV_DEG, "width": int(size), "height": int(size), "c2w_world": c2w.tolist()}


def write_relit_previews(query, world_from_norm, out_dir, center_world, radius_world: float, *,
                         up=(0.0, 0.0, 1.0), size: int = 256, bsdf_kind: str = "paper", device="cpu") -> list[Path]:
    """Render and write the canonical relit previews of ``query`` (a FieldQuery, normalised frame)
    into ``out_dir/previews``; returns the written paths (PNGs and the JSON record). The lobe is
    off when the query carries a shading without it (``ModelFieldQuery.shading``)."""
    from PIL import Image

    from nepf_core.data.scene import Scene
    from nepf_core.color import linear_to_srgb
    from nepf_core.rays import PixelSampler
    from nepf_core.relight.lights import lights_to_normalised
    from nepf_core.relight.render import query_surfaces, relight_views
    from nepf_core.relight.shade import ShadeOptions
    from nepf_core.relight.tracing import TraceConfig

    M = np.asarray(world_from_norm, np.float64)
    lights = canonical_lights(center_world, radius_world, up)
    cam = canonical_camera(center_world, radius_world, up, size)
    s = float(np.cbrt(abs(np.linalg.det(M[:3, :3]))))
    c2w = np.linalg.inv(M) @ np.asarray(cam["c2w_world"])
    c2w[:3, :3] *= s                       # back to a rotation (inv(M) scales by 1/s)
    f = 0.5 * size / math.tan(math.radians(CAMERA_FOV_DEG) / 2)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], np.float32)
    scene = Scene(images=np.zeros((1, size, size, 3), np.float32), masks=None, intrinsics=K[None],
                  c2w=c2w[None].astype(np.float32), world_from_norm=M, names=["canonical"])
    shading = getattr(query, "shading", None)
    opts = ShadeOptions(kind=bsdf_kind, specular=True if shading is None else bool(shading.specular))
    ln = lights_to_normalised(lights, M)
    rgb, _ = relight_views(query_surfaces(query, TraceConfig()), query.sdf, PixelSampler(scene, device),
                           ln.positions, ln.intensities, opts)
    prev = Path(out_dir) / "previews"
    prev.mkdir(parents=True, exist_ok=True)
    written = []
    for k in range(len(lights)):
        p = prev / f"relit_canonical_{k}.png"
        Image.fromarray((linear_to_srgb(np.clip(rgb[k, 0], 0, 1)) * 255 + 0.5).astype(np.uint8)).save(p)
        written.append(p)
    record = {"images": [p.name for p in written], "bsdf": bsdf_kind, "frame": "input world coordinates",
              "lights": lights.to_json()["lights"], "camera": {k: v for k, v in cam.items() if k != "c2w_world"},
              "canonical": {"azimuths_deg": list(CANONICAL_AZIMUTHS_DEG), "elevation_deg": CANONICAL_ELEVATION_DEG,
                            "distance": "3 x object radius", "center_world": list(map(float, center_world)),
                            "radius_world": float(radius_world)},
              "background": "black", "encoding": "sRGB of clip(linear radiance, 0, 1)"}
    (prev / RECORD).write_text(json.dumps(record, indent=1))
    return written + [prev / RECORD]
