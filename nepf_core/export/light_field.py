"""Light-field samples on the surface and a fitted light summary.

``light_field.json`` holds N area-uniform surface samples with the photon field's unit
direction to the light, its intensity and the surface normal. ``lights.json`` summarises them.
Both are computed in the input's world frame and written in the GLB's (+Y up,
:mod:`nepf_core.up_axis`; ``"frame": "glb"``), ``lights.json`` with its world-frame copy under
``"world"``. The summary:

* dominant direction ``d = normalize(sum_i I_i l_i)`` and its concentration
  ``|sum_i I_i l_i| / sum_i I_i`` (1 = all directions parallel);
* a point-light position: the weighted least-squares point closest to the lines
  ``x_i + t l_i``, i.e. ``argmin_p sum_i w_i |(I - l_i l_i^T)(p - x_i)|^2``, solved from
  ``(sum_i w_i P_i) p = sum_i w_i P_i x_i`` with ``P_i = I - l_i l_i^T`` and ``w_i = I_i``;
  one re-solve drops lines farther than ``3 * median`` from the first estimate;
* the point light's radiant intensity ``I_L = median_i(I_i |p - x_i|^2)`` (inverse-square);
* residual (weighted RMS line distance, absolute and relative to the object's size) and
  the conditioning ``lambda_min / lambda_max`` of ``sum_i w_i P_i``; when the lines are
  near-parallel (conditioning < 1e-3) or the point is > 100 object radii away, the light is
  reported as directional and ``point_light`` is null;
* ``confidence = exp(-(rms / radius) / 0.05) * min(1, conditioning / 0.01)`` in [0, 1]
  for a point light (1 = lines meet in one well-constrained point), 0 when directional.

With the learned global emitters (``model.light = "emitters"``, :mod:`nepf_core.fields.emitters`)
``lights.json`` also lists them as they are, under ``"emitters"``: each one's ``position`` and its
radiant intensity ``I_k s^2`` (:func:`emitters_to_world`); the fitted summary above then describes
the key emitter's share of the light field.

Intensities are the photon field's values (the field's units; for a world frame scaled by
``s`` the inverse-square intensity ``I_L`` is in world units, i.e. it scales by ``s^2``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import trimesh

from nepf_core.relight.lights import world_scale

from .mesh import directions_to_world, evaluate_in_chunks, mesh_to_world

__all__ = ["sample_light_field", "fit_lights", "emitters_to_world", "lights_to_frame", "write_light_field"]


def sample_light_field(
    light: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
    normal: Callable[[torch.Tensor], torch.Tensor],
    mesh_norm: trimesh.Trimesh,
    world_from_norm: np.ndarray,
    count: int = 4096,
    seed: int = 0,
    chunk: int = 65536,
    device: torch.device | str | None = None,
) -> dict[str, np.ndarray]:
    """Area-uniform samples on ``mesh_norm`` (normalised frame) -> light field in world frame.

    Returns dict of float arrays: ``points [N,3]``, ``normals [N,3]``, ``directions [N,3]``
    (unit, towards the light), ``intensity [N]``. Non-finite samples are dropped.
    """
    pts, face_idx = trimesh.sample.sample_surface(mesh_norm, int(count), seed=seed)
    pts = np.asarray(pts, dtype=np.float32)
    (nrm,) = evaluate_in_chunks(normal, pts, chunk=chunk, device=device, grad=True)
    fn = np.asarray(mesh_norm.face_normals[face_idx], dtype=np.float32)
    nl = np.linalg.norm(nrm, axis=-1, keepdims=True)
    ok_n = np.isfinite(nl[:, 0]) & (nl[:, 0] > 1e-8)
    nrm = np.where(ok_n[:, None], nrm / np.where(ok_n[:, None], nl, 1.0), fn)
    dirs, inten = evaluate_in_chunks(light, pts, nrm.astype(np.float32), chunk=chunk, device=device)
    dirs = dirs.reshape(-1, 3).astype(np.float64)
    inten = inten.reshape(-1).astype(np.float64)
    ok = np.isfinite(dirs).all(-1) & np.isfinite(inten) & (np.linalg.norm(dirs, axis=-1) > 1e-8)
    pw, nw = mesh_to_world(pts[ok], world_from_norm, nrm[ok])
    dw = directions_to_world(dirs[ok], world_from_norm)
    return {"points": pw, "normals": nw.astype(np.float64), "directions": dw,
            "intensity": np.maximum(inten[ok], 0.0)}


def fit_lights(points: np.ndarray, directions: np.ndarray, intensity: np.ndarray,
               object_radius: float | None = None) -> dict:
    """Fit the light summary described in the module docstring (world frame).

    Args: points ``[N,3]``, directions ``[N,3]`` unit, intensity ``[N]`` >= 0.
    Returns: JSON-able dict (see ``lights.json``).
    """
    x = np.asarray(points, dtype=np.float64)
    l = np.asarray(directions, dtype=np.float64)
    w = np.asarray(intensity, dtype=np.float64)
    if len(x) == 0:
        raise ValueError("fit_lights: no light samples")
    centre = x.mean(0)
    radius = float(object_radius or np.linalg.norm(x - centre, axis=-1).max() or 1.0)
    if w.sum() <= 0:
        w = np.ones_like(w)
    s = (w[:, None] * l).sum(0)
    concentration = float(np.linalg.norm(s) / w.sum())
    dominant = s / max(np.linalg.norm(s), 1e-12)

    def solve(mask: np.ndarray):
        ww = w[mask]
        ll = l[mask]
        xx = x[mask]
        proj = np.eye(3)[None] - ll[:, :, None] * ll[:, None, :]  # [N,3,3]
        a = (ww[:, None, None] * proj).sum(0)
        b = (ww[:, None, None] * proj @ xx[:, :, None])[..., 0].sum(0)
        ev = np.linalg.eigvalsh(a)
        p = np.linalg.lstsq(a, b, rcond=None)[0]
        dist = np.linalg.norm((proj @ (p - xx)[:, :, None])[..., 0], axis=-1)
        return p, dist, float(ev[0] / max(ev[-1], 1e-30))

    mask = np.ones(len(x), dtype=bool)
    p, dist_all, cond = solve(mask)
    if len(x) >= 8:
        med = np.median(dist_all)
        m2 = dist_all <= max(3.0 * med, 1e-9)
        if m2.sum() >= 4:
            mask = m2
            p, _, cond = solve(mask)
    v = p - x
    d = np.linalg.norm(v, axis=-1)
    dist = np.linalg.norm(v - (v * l).sum(-1, keepdims=True) * l, axis=-1)
    wm = w[mask]
    rms = float(np.sqrt((wm * dist[mask] ** 2).sum() / max(wm.sum(), 1e-30)))
    in_front = float(np.mean((v * l).sum(-1) > 0))  # fraction of samples that see p ahead
    far = np.linalg.norm(p - centre) > 100.0 * radius
    directional = cond < 1e-3 or far or in_front < 0.5
    point = None
    if not directional:
        point = {
            "position": p.tolist(),
            "intensity": float(np.median(w[mask] * d[mask] ** 2)),
            "residual_rms": rms,
            "residual_relative": rms / radius,
            "conditioning": cond,
            "fraction_in_front": in_front,
            "n_used": int(mask.sum()),
        }
    return {
        "frame": "world",
        "type": "directional" if directional else "point",
        "dominant_direction": dominant.tolist(),
        "direction_concentration": concentration,
        "mean_intensity": float(w.mean()),
        "point_light": point,
        "object_center": centre.tolist(),
        "object_radius": radius,
        "confidence": float(0.0 if directional
                            else np.exp(-rms / radius / 0.05) * min(1.0, cond / 1e-2)),
        "n_samples": int(len(x)),
    }


def emitters_to_world(positions, intensity, world_from_norm: np.ndarray) -> list[dict]:
    """The learned emitters ``positions [K, 3]`` (normalised frame) and radiant intensities ``I_k
    [K]`` in the world frame ``x_w = s R x + t``: ``position = M p_k`` and, since the irradiance
    ``I_k / |p_k - x|^2`` must not change when every distance grows by ``s``, intensity ``I_k s^2``
    with ``s = |det M[:3, :3]|^(1/3)`` (:func:`nepf_core.relight.lights.world_scale`). Listed
    brightest first."""
    p = np.asarray(torch.as_tensor(positions).detach().cpu(), np.float64).reshape(-1, 3)
    i = np.asarray(torch.as_tensor(intensity).detach().cpu(), np.float64).reshape(-1)
    m = np.asarray(world_from_norm, np.float64)
    scale2 = world_scale(m) ** 2
    pw, _ = mesh_to_world(p, m)
    order = np.argsort(-i, kind="stable")
    return [{"position": pw[k].tolist(), "intensity": float(i[k] * scale2)} for k in order]


def _rounded(a: np.ndarray, digits: int = 6) -> list:
    return np.round(np.asarray(a, dtype=np.float64), digits).tolist()


def lights_to_frame(lights: dict, rotation: np.ndarray, frame: str = "glb") -> dict:
    """``lights`` (a :func:`fit_lights` summary, world frame) in the frame ``x' = R x``.

    A rotation keeps lengths, so only the vectors move: ``dominant_direction``,
    ``object_center``, ``point_light.position`` and each ``emitters[k].position``; radii,
    residuals, intensities and the confidence are unchanged."""
    r = np.asarray(rotation, np.float64)
    out = {**lights, "frame": frame}
    out["dominant_direction"] = (r @ np.asarray(lights["dominant_direction"], np.float64)).tolist()
    out["object_center"] = (r @ np.asarray(lights["object_center"], np.float64)).tolist()
    if lights.get("point_light"):
        pl = dict(lights["point_light"])
        pl["position"] = (r @ np.asarray(pl["position"], np.float64)).tolist()
        out["point_light"] = pl
    if lights.get("emitters"):
        out["emitters"] = [{**e, "position": (r @ np.asarray(e["position"], np.float64)).tolist()}
                           for e in lights["emitters"]]
    return out


def write_light_field(out_dir: str | Path, field: dict[str, np.ndarray], lights: dict,
                      gltf_from_world: np.ndarray | None = None) -> list[Path]:
    """Write ``light_field.json`` (arrays rounded to 6 decimals) and ``lights.json``.

    ``field`` and ``lights`` are in the input's world frame. With ``gltf_from_world`` (``R``,
    :mod:`nepf_core.up_axis`) both files are written in the GLB's frame ``x_glb = R x_world``
    (``"frame": "glb"``, ``R`` recorded as ``gltf_from_world``) and ``lights.json`` keeps the
    world-frame summary under ``"world"``; without it, in the world frame (``"frame": "world"``).
    """
    out_dir = Path(out_dir)
    r = None if gltf_from_world is None else np.asarray(gltf_from_world, np.float64)
    rot = (lambda a: np.asarray(a, np.float64)) if r is None else (lambda a: np.asarray(a, np.float64) @ r.T)
    lf = {
        "frame": "world" if r is None else "glb",
        "count": int(len(field["points"])),
        "description": "area-uniform surface samples: points, unit normals, unit directions "
                       "towards the light, intensity (photon field units)",
        "points": _rounded(rot(field["points"])),
        "normals": _rounded(rot(field["normals"])),
        "directions": _rounded(rot(field["directions"])),
        "intensity": _rounded(field["intensity"]),
    }
    if r is not None:
        lf["gltf_from_world"] = r.tolist()
        lights = {**lights_to_frame(lights, r), "gltf_from_world": r.tolist(), "world": lights}
    paths = []
    for name, obj in (("light_field.json", lf), ("lights.json", lights)):
        p = out_dir / name
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_text(json.dumps(obj, separators=(",", ":") if name == "light_field.json" else None,
                                  indent=None if name == "light_field.json" else 2))
        tmp.replace(p)
        paths.append(p)
    return paths
