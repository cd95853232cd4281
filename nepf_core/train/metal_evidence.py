"""Where the images confirm a metal's lobe: the per-region evidence behind the unseen-lobe prior.

The prior ``w_metallic_unseen`` (:mod:`nepf_core.losses`) penalises ``m (1 - e(x))``: metallic
where nothing says the lobe is real. A per-ray ``e`` (the lobe's share in *this* view) cannot
tell a metal from a darkening knob: a metal's highlight reaches the camera from only a few of
the views around a point, so in most views its share is small and a per-ray prior turns a real
metal dielectric (bunny_metal, docs/FAST.md). The evidence must be gathered over views, per
region of the surface.

Per lit surface ray ``r`` (max-weight point ``x_r``, linear colours ``[R, 3]``), the point is
shaded under two hypotheses at its current albedo, roughness, normal and light: as a metal
(``l_r``, metallic 1: the GGX lobe with ``F0 = albedo``, no diffuse) and as a plain diffuse
(``d_r``, metallic 0, no lobe). Then

    q_r   = sum(l_r) / (sum(l_r) + sum(d_r))                    (would a metal's lobe show here?)
    rho_r = clip(<t_r - d_r, l_r> / <l_r, l_r>, 0, 1)           (how much of it the pixel t_r holds)
    e_r   = q_r * rho_r

Both are evaluated whatever the current metallic, so a metal that starts dielectric (metallic
near 0, where its current lobe is the 0.04 one and shows nowhere) still gathers evidence. A real
metal seen near its highlight: a metal's lobe dominates there (``q ~ 1``) and the pixel holds
it (``rho ~ 1``): ``e ~ 1``. A bright dielectric, or a dark texture passed off as a darkened
bright metal: a metal of that albedo would show a lobe ``a / 0.04`` times brighter than the
pixel's, ``rho ~ 0.04 / a`` is small even where the lobe is seen. A lobe no view sees (roughness
near 0, the highlight a point that no pixel catches): ``q ~ 0``.

The evidence is kept on a ``R^3`` grid over ``[-bound, bound]^3`` (the normalised frame) as a
decaying maximum: every step ``E <- decay * E``, then ``E[cell(x_r)] <- max(E, e_r)``;
``e(x) = E[cell(x)]``. ``decay = 0.5 ** (1 / half_life_steps)``: a cell on the surface is hit
every few steps at 1024 rays per batch, so a highlight view of a region is seen again well
within a half-life, while evidence from an earlier, wrong geometry or light fades.
"""

from __future__ import annotations

import torch
from torch import Tensor


def lobe_confirmation(metal_lobe: Tensor, diffuse: Tensor, target: Tensor) -> Tensor:
    """``e_r = q_r rho_r`` (module docstring) for ``[R, 3]`` linear colours: the point shaded as
    a metal, shaded as a plain diffuse, and the pixel. ``[R]`` in [0, 1]; 0 where the lobe is
    (numerically) absent."""
    q = metal_lobe.sum(-1).clamp_min(0) / (metal_lobe + diffuse).sum(-1).clamp_min(1e-6)
    ll = (metal_lobe * metal_lobe).sum(-1)
    rho = ((target - diffuse) * metal_lobe).sum(-1) / ll.clamp_min(1e-12)
    rho = torch.where(ll > 1e-12, rho, torch.zeros_like(rho)).clamp(0.0, 1.0)
    return (q * rho).clamp(0.0, 1.0)


class MetalEvidence:
    """The decaying-maximum grid of :func:`lobe_confirmation` (module docstring); run state of
    one fit, saved in its checkpoints."""

    def __init__(self, resolution: int = 32, bound: float = 1.0, half_life_steps: float = 200.0,
                 device: torch.device | str = "cpu") -> None:
        if resolution < 1 or bound <= 0 or half_life_steps <= 0:
            raise ValueError("MetalEvidence needs resolution >= 1, bound > 0 and half_life_steps > 0")
        self.resolution, self.bound = int(resolution), float(bound)
        self.decay = 0.5 ** (1.0 / float(half_life_steps))
        self.grid = torch.zeros(self.resolution ** 3, device=device)

    def cells(self, x: Tensor) -> Tensor:
        """Flat cell index ``[N]`` of points ``[N, 3]``; points outside go to the border cells."""
        R = self.resolution
        ijk = ((x + self.bound) / (2 * self.bound) * R).floor().long().clamp(0, R - 1)
        return (ijk[:, 0] * R + ijk[:, 1]) * R + ijk[:, 2]

    @torch.no_grad()
    def observe(self, x: Tensor, evidence: Tensor, keep: Tensor) -> None:
        """One step: decay every cell, then raise the cells of the kept points ``x [N, 3]`` to
        their ``evidence [N]`` (``keep [N]`` bool: lit surface rays)."""
        self.grid.mul_(self.decay)
        if bool(keep.any()):
            self.grid.scatter_reduce_(0, self.cells(x[keep].detach()), evidence[keep].detach().float(), reduce="amax")

    @torch.no_grad()
    def observe_render(self, out, rays, use_mask: bool) -> Tensor:
        """One training render (``need_metal_hypothesis``): observe its lit surface rays (the rays
        ``L_unseen`` averages over: mask, or ``sum w > 0.5`` without one, less the unlit pixels)
        and return ``e(x) [R]`` at every ray's surface point, for ``surf["metal_evidence"]``."""
        s = out.surf
        on_surf = (rays.mask > 0.5) if (use_mask and rays.mask is not None) else (out.weight_sum.detach() > 0.5)
        lit = on_surf & ~rays.unlit if rays.unlit is not None else on_surf
        self.observe(s["x"], lobe_confirmation(s["metal_lobe_rgb"], s["dielectric_diffuse_rgb"], rays.rgb), lit)
        return self.lookup(s["x"])

    def lookup(self, x: Tensor) -> Tensor:
        """``e(x) [N]`` for points ``x [N, 3]`` (no gradient)."""
        return self.grid[self.cells(x.detach())]

    def state_dict(self) -> dict:
        return {"grid": self.grid.detach().cpu(), "resolution": self.resolution, "bound": self.bound,
                "decay": self.decay}

    def load_state_dict(self, s: dict) -> None:
        if int(s["resolution"]) != self.resolution:
            raise ValueError(f"metal evidence grid is {s['resolution']}^3 in the checkpoint, {self.resolution}^3 here")
        self.grid = s["grid"].to(self.grid.device).float()
        self.bound, self.decay = float(s["bound"]), float(s["decay"])
