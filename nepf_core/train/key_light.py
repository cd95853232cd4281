"""A global key light fitted to the foreground pixels' brightness, the surface points and normals.

The photon field may point each surface point's light anywhere, and on the suite it settles
12-105 deg from the true key (bench/RESULTS.md v48) before the lobe gives up on the highlights.
The pixels say where the key is whatever the materials: a surface lit by one dominant light is
brightest where it faces it and dark past its terminator. The model, over foreground rays
(surface points ``x`` and normals ``n`` detached, ``y`` the pixel's linear luminance clipped to 1)::

    y ~ a max(n . d(x), 0) / |p - x|^2 + b,      d(x) = (p - x) / |p - x|,   a >= 0

for a point light at ``p`` (normalised frame), or ``y ~ a max(n . u, 0) + b`` for a distant one.
Fitted robustly (soft-L1, scale :data:`ROBUST_SCALE`): a search over :data:`LATTICE` directions
from the points' centre at :data:`DISTANCES` and at infinity, the closed-form ``(a, b)`` of each,
re-weighted, then refined by tilts and distance steps. A point light is kept only where it
explains the pixels clearly better than the best distant one (robust cost under
:data:`POINT_GAIN` of it): on a metal, whose diffuse is missing, the distance is not fixed by the
shading, and a near light fitted there is wrong by tens of degrees (v48).

The training term (``loss.w_key_light``) pulls the photon direction of each lit ray whose normal
faces the key toward it, ``L = w mean (1 - l(x*) . d(x*))``; a point facing away is left free
(a fill light, a shadow).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

LATTICE = 256
"""Candidate directions of the search (a Fibonacci lattice, ~13 deg apart; the tilts refine)."""
DISTANCES = (1.5, 2.0, 3.0, 4.5, 7.0, 12.0)
"""Candidate distances of a point light from the points' centre (normalised frame: the object
lies in the unit ball)."""
FAR = 1.0e4
"""A distant light's stand-in distance."""
ROBUST_SCALE = 0.05
"""Soft-L1 scale of the residual (linear luminance)."""
POINT_GAIN = 0.9
"""A point light is kept when its robust cost is under this share of the best distant light's."""
CAPACITY = 4096
"""Rays ``(x, n, y)`` kept (the latest)."""
FIRST_FIT_STEP = 100
KEY_LIGHT_UNTIL = 0.5
"""The term acts over this share of the run (the materials are chosen early; later the field is free)."""
REFIT_EVERY = 100
FIT_POINTS = 2048
"""Rays of the buffer each fit uses (evenly strided)."""
MIN_EXPLAINED = 0.5
"""The key is used only where it explains at least this share of the pixels' robust cost (a
surface the diffuse model explains: 0.75-1.0 on the suite's dielectrics, 0.00-0.16 on its metals,
whose missing diffuse leaves the light unfixed, v48)."""


def fibonacci_directions(count: int, dtype=torch.float32, device=None) -> Tensor:
    """``[count, 3]`` unit vectors spread evenly over the sphere (``z_i = 1 - (2 i + 1) / count``,
    azimuth ``i`` golden angles)."""
    i = torch.arange(count, dtype=torch.float64, device=device)
    z = 1.0 - (2.0 * i + 1.0) / count
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    s = (1.0 - z * z).sqrt()
    return torch.stack([s * phi.cos(), s * phi.sin(), z], -1).to(dtype)


def _tilts(u: Tensor, deg: float, count: int = 8) -> Tensor:
    """``[count, 3]``: ``u`` tilted by ``deg`` at ``count`` azimuths."""
    helper = u.new_tensor([1.0, 0.0, 0.0]) if abs(float(u[0])) < 0.9 else u.new_tensor([0.0, 1.0, 0.0])
    t1 = torch.nn.functional.normalize(torch.linalg.cross(u, helper), dim=0)
    t2 = torch.linalg.cross(u, t1)
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    phis = torch.arange(count, dtype=u.dtype, device=u.device) * (2.0 * math.pi / count)
    return c * u + s * (phis.cos()[:, None] * t1 + phis.sin()[:, None] * t2)


def _shading(p: Tensor, x: Tensor, n: Tensor) -> Tensor:
    """``[C, N]``: ``max(n . d, 0) / |p - x|^2`` for candidate lights ``p [C, 3]``, scaled per
    candidate by its mean ``|p - x|^2`` (so that a distant light's values stay O(1))."""
    d = p[:, None, :] - x[None]
    r2 = (d * d).sum(-1)
    return ((d * n[None]).sum(-1) / r2.sqrt()).clamp_min(0.0) * (r2.mean(1, keepdim=True) / r2)


def _robust_costs(p: Tensor, x: Tensor, n: Tensor, y: Tensor, rounds: int) -> Tensor:
    """``[C]`` the soft-L1 cost of each candidate after ``rounds`` re-weightings of ``(a, b)``."""
    s = _shading(p, x, n)
    w = torch.ones_like(s)
    for _ in range(rounds + 1):
        sw, s2, ww = (w * s).sum(1), (w * s * s).sum(1), w.sum(1)
        sy, yy = (w * s * y).sum(1), (w * y).sum(1)
        a = ((sy * ww - sw * yy) / (s2 * ww - sw * sw).clamp_min(1e-12)).clamp_min(0.0)
        b = (yy - a * sw) / ww.clamp_min(1e-12)
        r = a[:, None] * s + b[:, None] - y[None]
        w = 1.0 / (1.0 + (r / ROBUST_SCALE) ** 2).sqrt()
    return (2.0 * ROBUST_SCALE ** 2 * ((1.0 + (r / ROBUST_SCALE) ** 2).sqrt() - 1.0)).sum(1)


def _refine(best: Tensor, centre: Tensor, x, n, y, distant: bool) -> tuple[Tensor, float]:
    """Tilts of 6, 3, 1.5 and 0.75 deg about the centre and (a point light) distance steps of 25 %."""
    for deg in (6.0, 3.0, 1.5, 0.75):
        off = best - centre
        dist, u = off.norm(), off / off.norm()
        cand = [best[None], centre + dist * _tilts(u, deg)]
        if not distant:
            cand += [(centre + u * dist * 1.25)[None], (centre + u * dist / 1.25)[None]]
        cand = torch.cat(cand)
        cost = _robust_costs(cand, x, n, y, 3)
        best = cand[cost.argmin()]
    return best, float(cost.min())


@dataclass
class KeyLight:
    """The fitted key: ``position [3]`` (normalised frame) of a point light, or ``direction [3]``
    of a distant one (the other None)."""

    position: Tensor | None
    direction: Tensor | None
    explained: float = 1.0
    """``1 - cost / cost of the best constant``: how much of the pixels the light explains."""

    def log_falloff(self, x: Tensor) -> Tensor:
        """``[N]``: ``-log |p - x|^2`` (0 for a distant key): the log of the irradiance's falloff
        up to a constant."""
        if self.position is None:
            return x.new_zeros(x.shape[0])
        return -torch.log(((self.position.to(x)[None] - x) ** 2).sum(-1).clamp_min(1e-12))

    def toward(self, x: Tensor) -> Tensor:
        """``[N, 3]`` unit directions from the points ``x [N, 3]`` toward the key."""
        if self.position is None:
            return self.direction.to(x)[None].expand_as(x)
        return torch.nn.functional.normalize(self.position.to(x)[None] - x, dim=-1)


@torch.no_grad()
def fit_key_light(x: Tensor, n: Tensor, y: Tensor, shortlist: int = 16) -> KeyLight:
    """The key of the module docstring from points ``x [N, 3]``, unit normals ``n [N, 3]`` and
    luminances ``y [N]``."""
    x, n, y = x.double(), n.double(), y.double()
    centre = x.mean(0)
    lattice = fibonacci_directions(LATTICE, torch.float64, x.device)
    best = {}
    for distant, dists in ((True, (FAR,)), (False, DISTANCES)):
        cand = torch.cat([centre + d * lattice for d in dists])
        ls = torch.cat([_robust_costs(c, x, n, y, 0) for c in cand.split(1024)])
        short = cand[ls.topk(min(shortlist, len(cand)), largest=False).indices]
        start = short[_robust_costs(short, x, n, y, 3).argmin()]
        best[distant] = _refine(start, centre, x, n, y, distant)
    (p_far, c_far), (p_near, c_near) = best[True], best[False]
    flat = _flat_cost(y)
    if c_near < POINT_GAIN * c_far:
        return KeyLight(position=p_near.float(), direction=None, explained=1.0 - c_near / flat)
    return KeyLight(position=None, direction=torch.nn.functional.normalize(p_far - centre, dim=0).float(),
                    explained=1.0 - c_far / flat)


def _flat_cost(y: Tensor) -> float:
    """The soft-L1 cost of the best constant (no light): its IRLS from the mean."""
    b = y.mean()
    for _ in range(4):
        w = 1.0 / (1.0 + ((y - b) / ROBUST_SCALE) ** 2).sqrt()
        b = (w * y).sum() / w.sum()
    r = y - b
    return float((2.0 * ROBUST_SCALE ** 2 * ((1.0 + (r / ROBUST_SCALE) ** 2).sqrt() - 1.0)).sum().clamp_min(1e-12))


class KeyLightEstimate:
    """The latest :data:`CAPACITY` foreground rays and the key fitted to them (``key``, None
    before step :data:`FIRST_FIT_STEP`), refitted every :data:`REFIT_EVERY` steps."""

    def __init__(self, device) -> None:
        self.x = torch.zeros(0, 3, device=device)
        self.n = torch.zeros(0, 3, device=device)
        self.y = torch.zeros(0, device=device)
        self.key: KeyLight | None = None
        self.last_fit: KeyLight | None = None

    @torch.no_grad()
    def add(self, x: Tensor, n: Tensor, y: Tensor) -> None:
        self.x = torch.cat([self.x, x.detach().float()])[-CAPACITY:]
        self.n = torch.cat([self.n, n.detach().float()])[-CAPACITY:]
        self.y = torch.cat([self.y, y.detach().float()])[-CAPACITY:]

    def maybe_refit(self, step: int) -> bool:
        """Refit at this step if it is one (True when it did)."""
        if step < FIRST_FIT_STEP or (step - FIRST_FIT_STEP) % REFIT_EVERY or self.x.shape[0] < 256:
            return False
        stride = max(1, self.x.shape[0] // FIT_POINTS)
        key = fit_key_light(self.x[::stride], torch.nn.functional.normalize(self.n[::stride], dim=-1), self.y[::stride])
        self.key = key if key.explained >= MIN_EXPLAINED else None
        self.last_fit = key
        return True
