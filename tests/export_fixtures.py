"""Analytic FieldQuery fixtures for the export tests (no network, no ../shared).

``SphereQuery`` is a sphere of radius ``r`` centred at ``c`` (normalised frame) with

* SDF ``f(x) = |x - c| - r``, normal ``(x - c) / |x - c|``;
* albedo ``a(x) = (0.5 + 0.4 u_x, 0.5 + 0.4 u_y, 0.5 + 0.4 u_z)`` with ``u = (x - c) / r``
  (spatially varying, in [0.1, 0.9], linear RGB);
* roughness 0.3 and metallic 0.7 everywhere;
* a point light at ``p`` with radiant intensity ``I0``: direction ``(p - x) / |p - x|``,
  intensity ``I0 / |p - x|^2``.
"""

from __future__ import annotations

import numpy as np
import torch

ROUGHNESS = 0.3
METALLIC = 0.7


class SphereQuery:
    """FieldQuery for an analytic sphere (see module docstring)."""

    def __init__(self, radius: float = 0.6, center=(0.05, -0.02, 0.03), light_pos=(1.5, 1.0, 2.0),
                 light_intensity: float = 4.0, empty: bool = False):
        self.radius = float(radius)
        self.center = torch.tensor(center, dtype=torch.float32)
        self.light_pos = torch.tensor(light_pos, dtype=torch.float32)
        self.light_intensity = float(light_intensity)
        self.empty = empty

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        d = (x - self.center).norm(dim=-1) - self.radius
        return d.abs() + 0.25 if self.empty else d

    def normal(self, x: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.normalize(x - self.center, dim=-1)

    def material(self, x: torch.Tensor, n: torch.Tensor):
        return albedo_torch(x, self.center, self.radius), \
            torch.full(x.shape[:1], ROUGHNESS), torch.full(x.shape[:1], METALLIC)

    def light(self, x: torch.Tensor, n: torch.Tensor):
        v = self.light_pos - x
        d2 = (v * v).sum(-1)
        return v / d2.sqrt()[:, None], self.light_intensity / d2


def albedo_torch(x: torch.Tensor, center: torch.Tensor, radius: float) -> torch.Tensor:
    u = (x - center) / radius
    return (0.5 + 0.4 * u).clamp(0.0, 1.0)


def albedo_numpy(x_norm: np.ndarray, center, radius: float) -> np.ndarray:
    """Known albedo at normalised-frame points ``[N,3]`` -> ``[N,3]``."""
    u = (x_norm - np.asarray(center)) / radius
    return np.clip(0.5 + 0.4 * u, 0.0, 1.0)


def similarity(scale: float = 2.5, translation=(3.0, -1.0, 0.5), angle_deg: float = 30.0) -> np.ndarray:
    """``world_from_norm = [s R | t]`` with R a rotation about the axis (1,1,0)/sqrt(2)."""
    k = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    a = np.deg2rad(angle_deg)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    r = np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx
    m = np.eye(4)
    m[:3, :3] = scale * r
    m[:3, 3] = translation
    return m
