"""Analytic shapes (signed distance functions) and material presets for the scene maker.

All SDFs are exact Euclidean distances in *object* units (object inside the unit ball,
Z up), torch ``[..., 3] -> [...]``, any float dtype:

* ``sphere``:  ``|p| - 1``
* ``torus``:   major radius 0.7, minor 0.3, its axis tilted 20 deg about x (as the shared
  ``torus_*`` scenes): ``q = R_x(-20deg) p``, ``|(|q_xy| - 0.7, q_z)| - 0.3``
* ``box``:     rounded box, half extents (0.6, 0.5, 0.4), edge radius 0.08:
  ``q = |p| - (b - r)``, ``|max(q, 0)| + min(max_i q_i, 0) - r``
* ``capsule``: segment (0, 0, -0.45)..(0, 0, 0.45), radius 0.5:
  ``|p - a - clamp((p-a).(b-a)/|b-a|^2, 0, 1)(b - a)| - 0.5``
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

TORUS_TILT_DEG = 20.0


def sdf_sphere(p: Tensor) -> Tensor:
    """Unit sphere: ``|p| - 1``."""
    return p.norm(dim=-1) - 1.0


def _rot_x(p: Tensor, deg: float) -> Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    x, y, z = p.unbind(-1)
    return torch.stack([x, c * y - s * z, s * y + c * z], -1)


def sdf_torus(p: Tensor) -> Tensor:
    """Tilted torus R = 0.7, r = 0.3 (bounding radius 1)."""
    q = _rot_x(p, -TORUS_TILT_DEG)
    ring = torch.sqrt(q[..., 0] ** 2 + q[..., 1] ** 2) - 0.7
    return torch.sqrt(ring ** 2 + q[..., 2] ** 2) - 0.3


def sdf_box(p: Tensor) -> Tensor:
    """Rounded box, half extents (0.6, 0.5, 0.4), edge radius 0.08 (bounding radius 0.877)."""
    r = 0.08
    b = torch.tensor([0.6, 0.5, 0.4], dtype=p.dtype, device=p.device)
    q = p.abs() - (b - r)
    outside = q.clamp_min(0.0).norm(dim=-1)
    inside = q.max(dim=-1).values.clamp_max(0.0)
    return outside + inside - r


def sdf_capsule(p: Tensor) -> Tensor:
    """Capsule along z, half length 0.45, radius 0.5 (bounding radius 0.95)."""
    z = p[..., 2].clamp(-0.45, 0.45)
    d = p - torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], -1)
    return d.norm(dim=-1) - 0.5


SHAPES = {"sphere": sdf_sphere, "torus": sdf_torus, "box": sdf_box, "capsule": sdf_capsule}

#: Material presets: ``albedo`` (linear RGB or ``"checker"``), ``roughness``, ``metallic``, and
#: the BSDF switches passed to :func:`nepf_core.bsdf.shade`.
MATERIALS = {
    "diffuse": {"albedo": (0.75, 0.55, 0.35), "roughness": 1.0, "metallic": 0.0,
                "lambertian": True, "specular": False},
    "glossy": {"albedo": (0.15, 0.35, 0.75), "roughness": 0.25, "metallic": 0.0,
               "lambertian": False, "specular": True},
    "metal": {"albedo": (0.95, 0.64, 0.54), "roughness": 0.3, "metallic": 1.0,
              "lambertian": False, "specular": True},
    "mirror": {"albedo": (0.9, 0.9, 0.9), "roughness": 0.02, "metallic": 1.0,
               "lambertian": False, "specular": True},
    "textured": {"albedo": "checker", "roughness": 0.5, "metallic": 0.0,
                 "lambertian": False, "specular": True},
}

#: The two albedos of the 3D checker and its cell size (object units).
CHECKER_COLOURS = ((0.85, 0.25, 0.15), (0.15, 0.55, 0.85))
CHECKER_CELL = 0.4


def checker_albedo(p: Tensor) -> Tensor:
    """3D checker: colour ``(floor(x/c) + floor(y/c) + floor(z/c)) mod 2``; ``[..., 3] -> [..., 3]``."""
    k = torch.floor(p / CHECKER_CELL).sum(-1).remainder(2.0)[..., None]
    a = torch.tensor(CHECKER_COLOURS[0], dtype=p.dtype, device=p.device)
    b = torch.tensor(CHECKER_COLOURS[1], dtype=p.dtype, device=p.device)
    return a * (1.0 - k) + b * k
