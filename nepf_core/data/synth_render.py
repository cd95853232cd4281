"""Sphere-tracing renderer for the scene maker (torch, CPU, float64, object units).

Per ray ``x(t) = o + t d`` (``d`` unit):
    * start at the entry into the bounding ball ``|x| <= BOUND``, step ``t <- t + f(x(t))``
      (exact SDFs, so no over-step), hit when ``f < HIT_EPS``;
    * normal ``n = grad f / |grad f|`` by central differences (step 1e-6);
    * one point light at ``p_L`` with radiant intensity ``I``:
      ``L = shade(n, l, v, albedo, r, m, I / |p_L - x|^2 * V) + ambient * albedo``, with
      ``l = (p_L - x)/|p_L - x|``, ``v = -d`` and ``V`` a hard shadow (a second sphere trace
      from ``x + 1e-3 n`` towards the light);
    * pixels are supersampled ``ss x ss`` and box-averaged: ``alpha`` is the hit fraction
      and colours are premultiplied by it (background black).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nepf_core.bsdf import shade
from nepf_core.data.synth_shapes import MATERIALS, SHAPES, checker_albedo

BOUND = 1.05
HIT_EPS = 1e-5
MAX_STEPS = 256


@dataclass
class Material:
    """Resolved material: ``albedo`` (3 floats or ``"checker"``), ``roughness``, ``metallic``, BSDF switches."""

    albedo: tuple | str
    roughness: float
    metallic: float
    lambertian: bool = False
    specular: bool = True

    @classmethod
    def resolve(cls, preset: str, albedo=None, roughness=None, metallic=None) -> "Material":
        """Preset from :data:`MATERIALS` with any explicit value overriding it."""
        if preset not in MATERIALS:
            raise ValueError(f"unknown material '{preset}' (one of {sorted(MATERIALS)})")
        m = dict(MATERIALS[preset])
        if albedo is not None:
            m["albedo"] = tuple(float(a) for a in albedo)
        if roughness is not None:
            m["roughness"] = float(roughness)
        if metallic is not None:
            m["metallic"] = float(metallic)
        return cls(**m)

    def albedo_at(self, x: Tensor) -> Tensor:
        """``[M, 3] -> [M, 3]`` linear albedo."""
        if self.albedo == "checker":
            return checker_albedo(x)
        return torch.tensor(self.albedo, dtype=x.dtype).expand(x.shape[0], 3)

    def to_json(self) -> dict:
        return {"albedo": self.albedo if isinstance(self.albedo, str) else list(self.albedo),
                "roughness": self.roughness, "metallic": self.metallic,
                "bsdf": {"lambertian": self.lambertian, "specular": self.specular}}


def ball_interval(o: Tensor, d: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Entry/exit ``t`` of rays ``[M, 3]`` through ``|x| <= radius`` (``t0 > t1`` on a miss)."""
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - radius * radius
    disc = b * b - c
    s = disc.clamp_min(0.0).sqrt()
    t0 = (-b - s).clamp_min(0.0)
    t1 = torch.where(disc >= 0, -b + s, torch.full_like(b, -1.0))
    return t0, t1


def sphere_trace(sdf, o: Tensor, d: Tensor, t0: Tensor, t1: Tensor) -> tuple[Tensor, Tensor]:
    """March rays to the surface: returns ``hit [M] bool``, ``t [M]``.

    Works on compacted copies of the still-active rays (finished rays are written back and
    dropped each step). A ray that runs out of :data:`MAX_STEPS` (grazing the surface)
    counts as a hit when its last distance is below ``1e-3``.
    """
    t = t0.clone()
    hit = torch.zeros_like(t, dtype=torch.bool)
    idx = torch.nonzero(t0 <= t1).squeeze(-1)
    oa, da, ta, t1a = o[idx], d[idx], t0[idx], t1[idx]
    f = None
    for _ in range(MAX_STEPS):
        if idx.numel() == 0:
            break
        f = sdf(oa + ta[:, None] * da)
        done = f < HIT_EPS
        ta = ta + f.clamp_min(0.0)
        out = ta > t1a
        stop = done | out
        if stop.any():
            hit[idx[done]] = True
            t[idx[stop]] = ta[stop]
            keep = ~stop
            idx, oa, da, ta, t1a = idx[keep], oa[keep], da[keep], ta[keep], t1a[keep]
            f = f[keep]
    if idx.numel() and f is not None:
        t[idx] = ta
        hit[idx] = f < 1e-3
    return hit, t


def sdf_normal(sdf, x: Tensor, eps: float = 1e-6) -> Tensor:
    """Unit SDF gradient by central differences: ``[M, 3] -> [M, 3]``."""
    g = torch.empty_like(x)
    for k in range(3):
        e = torch.zeros(3, dtype=x.dtype)
        e[k] = eps
        g[:, k] = sdf(x + e) - sdf(x - e)
    return g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def shadow_visibility(sdf, x: Tensor, n: Tensor, light: Tensor) -> Tensor:
    """``[M]`` 1 where the light is visible from ``x`` (hard shadow), else 0."""
    o = x + 1e-3 * n
    to_l = light - o
    dist = to_l.norm(dim=-1)
    d = to_l / dist[:, None]
    t0 = torch.zeros_like(dist)
    _, t1 = ball_interval(o, d, BOUND)
    t1 = torch.minimum(t1, dist)
    hit, _ = sphere_trace(sdf, o, d, t0, t1)
    return (~hit).to(x.dtype)


def render_rays(shape: str, material: Material, o: Tensor, d: Tensor, light_pos: Tensor,
                light_intensity: float, ambient: float) -> dict[str, Tensor]:
    """Render rays ``o, d [M, 3]`` (object units). Returns per ray:
    ``rgb [M, 3]`` linear radiance, ``hit [M]``, ``albedo [M, 3]``, ``roughness [M]``,
    ``metallic [M]``, ``normal [M, 3]``, ``t [M]`` (zeros where there is no hit)."""
    sdf = SHAPES[shape]
    M = o.shape[0]
    t0, t1 = ball_interval(o, d, BOUND)
    hit, t = sphere_trace(sdf, o, d, t0, t1)
    out = {"rgb": torch.zeros(M, 3, dtype=o.dtype), "hit": hit,
           "albedo": torch.zeros(M, 3, dtype=o.dtype), "roughness": torch.zeros(M, dtype=o.dtype),
           "metallic": torch.zeros(M, dtype=o.dtype), "normal": torch.zeros(M, 3, dtype=o.dtype),
           "t": torch.zeros(M, dtype=o.dtype)}
    idx = torch.nonzero(hit).squeeze(-1)
    if idx.numel() == 0:
        return out
    x = o[idx] + t[idx, None] * d[idx]
    n = sdf_normal(sdf, x)
    to_l = light_pos - x
    dist2 = (to_l * to_l).sum(-1, keepdim=True)
    l = to_l / dist2.sqrt()
    v = -d[idx]
    vis = shadow_visibility(sdf, x, n, light_pos)[:, None]
    alb = material.albedo_at(x)
    r = torch.full((idx.numel(), 1), material.roughness, dtype=o.dtype)
    m = torch.full((idx.numel(), 1), material.metallic, dtype=o.dtype)
    L = shade(n, l, v, alb, r, m, light_intensity / dist2 * vis,
              lambertian=material.lambertian, specular=material.specular)
    out["rgb"][idx] = L + ambient * alb
    out["albedo"][idx] = alb
    out["roughness"][idx] = r[:, 0]
    out["metallic"][idx] = m[:, 0]
    out["normal"][idx] = n
    out["t"][idx] = t[idx]
    return out


def pixel_rays(K: np.ndarray, c2w: np.ndarray, w: int, h: int, ss: int) -> tuple[Tensor, Tensor]:
    """Rays through ``ss x ss`` sub-pixel centres ``(u + (i + 0.5)/ss, v + (j + 0.5)/ss)``
    (pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)``, Scene convention), OpenCV camera.
    Returns ``o, d`` of shape ``[H*W*ss*ss, 3]`` ordered (v, u, j, i)."""
    sub = (np.arange(ss) + 0.5) / ss
    us = (np.arange(w)[:, None] + sub[None]).reshape(-1)
    vs = (np.arange(h)[:, None] + sub[None]).reshape(-1)
    U, V = np.meshgrid(us, vs)  # [H*ss, W*ss]
    pix = np.stack([U, V, np.ones_like(U)], -1).reshape(-1, 3)
    dirs_cam = pix @ np.linalg.inv(K).T
    dirs = dirs_cam @ c2w[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    o = np.broadcast_to(c2w[:3, 3], dirs.shape)
    return torch.from_numpy(np.ascontiguousarray(o)), torch.from_numpy(dirs)


def render_views(shape: str, material: Material, Ks: np.ndarray, c2ws: np.ndarray, w: int, h: int,
                 ss: int, light_pos, light_intensity: float, ambient: float) -> dict[str, np.ndarray]:
    """Render ``N`` views in one batch (object units). Returns float32 maps ``[N, H, W, ...]``,
    box-averaged over ``ss x ss`` samples: ``rgb [N, H, W, 3]`` (premultiplied, linear,
    before exposure), ``alpha [N, H, W]``, ``albedo [N, H, W, 3]``, ``roughness``,
    ``metallic`` ``[N, H, W]``, ``normal [N, H, W, 3]`` (unit, zero on background) and
    ``depth_z [N, H, W]`` (camera z, object units); material maps and depth are averaged
    over the samples that hit."""
    n = len(Ks)
    rays = [pixel_rays(K, c2w, w, h, ss) for K, c2w in zip(Ks, c2ws)]
    o = torch.cat([r[0] for r in rays])
    d = torch.cat([r[1] for r in rays])
    fwd = torch.cat([torch.from_numpy(np.ascontiguousarray(c2w[:3, 2])).expand(len(r[1]), 3)
                     for c2w, r in zip(c2ws, rays)])
    r = render_rays(shape, material, o, d, torch.as_tensor(light_pos, dtype=torch.float64),
                    light_intensity, ambient)

    def box(x: Tensor) -> np.ndarray:
        a = x.reshape(n, h, ss, w, ss, *x.shape[1:]).numpy()
        return a.mean(axis=(2, 4))

    alpha = box(r["hit"].to(torch.float64))
    cover = np.maximum(alpha, 1e-12)
    depth = r["t"] * (d * fwd).sum(-1)
    out = {"rgb": box(r["rgb"]), "alpha": alpha}
    for k, x in (("albedo", r["albedo"]), ("roughness", r["roughness"]),
                 ("metallic", r["metallic"]), ("normal", r["normal"]), ("depth_z", depth)):
        v = box(x)
        out[k] = v / (cover[..., None] if v.ndim == 4 else cover)
    nrm = np.linalg.norm(out["normal"], axis=-1, keepdims=True)
    out["normal"] = np.where(nrm > 1e-9, out["normal"] / np.maximum(nrm, 1e-12), 0.0)
    return {k: v.astype(np.float32) for k, v in out.items()}
