"""Stage 3 of the renderer: the surface point of each ray and what is shaded there.

:class:`Surface` holds, per ray, the point ``x*`` where ``L_surf`` is shaded and the fields
there (normal, light, material). ``x*`` is the max-weight sample ``x_{i*}``, ``i* = argmax_i w_i``,
or with ``RenderConfig.surface_refine`` (sample alpha mode) the SDF zero crossing inside the
max-weight section (:func:`refine_surface`): the max-weight sample lies up to one sample
spacing in front of the surface, at an offset that changes with the sample placement.

Extra evidence is asked for with a :class:`SurfaceRequest` (the loss terms' and the rules'
union, built by the training loop) and comes back typed: :class:`LobeSplit`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from nepf_core import bsdf
from nepf_core.fields.fd_normals import fd_stencil, gradient_from_stencil
from nepf_core.render.neus import surface_crossing_t


@dataclass
class MaterialSample:
    """The material at jittered points ``x* + N(0, sigma^2 I)`` (the smoothness priors):
    ``albedo [R, 3]``, ``roughness [R]``, ``metallic [R]``."""

    albedo: Tensor
    roughness: Tensor
    metallic: Tensor
    normal: Tensor | None = None
    """``[R, 3]`` the SDF's unit normal at the jittered points (only with ``surface_refine``)."""
    normal_mirror: Tensor | None = None
    """``[R, 3]`` the SDF's unit normal at the mirrored points ``2 x* - x_j`` (with ``normal``)."""


@dataclass
class LobeSplit:
    """The GGX lobe's part of ``L_surf`` (no grad): ``diffuse_only [R, 3]`` is ``L_surf`` shaded
    without the lobe, ``share [R] = max(0, sum_c (L_surf - L_d)) / max(sum_c L_surf, 1e-6)`` the
    lobe's share of it and ``absolute [R] = mean_c max(0, L_surf - L_d)`` its size."""

    diffuse_only: Tensor
    share: Tensor
    absolute: Tensor


@dataclass
class Surface:
    """Per ray (``R``): the surface point ``x*`` and the fields there, all fp32."""

    x: Tensor
    """``[R, 3]`` the point (normalised frame)."""
    normal: Tensor
    """``[R, 3]`` unit SDF normal."""
    direction: Tensor
    """``[R, 3]`` the ray direction ``d`` (view direction ``v = -d``)."""
    light_dir: Tensor
    """``[R, 3]`` unit direction to the light."""
    intensity: Tensor
    """``[R]`` the light's radiant intensity at ``x*``."""
    albedo: Tensor
    """``[R, 3]`` in [0, 1]."""
    roughness: Tensor
    """``[R]`` in [0, 1]."""
    metallic: Tensor
    """``[R]`` in [0, 1]."""
    material_logits: Tensor | None = None
    """``[R, 5]`` the material network's raw outputs (training renders only)."""
    lights: tuple[Tensor, Tensor] | None = None
    """With global emitters (:mod:`nepf_core.fields.emitters`): every light's ``(directions
    [R, K, 3], irradiance [R, K])``; ``light_dir``/``intensity`` are the dominant one's."""
    jitter: MaterialSample | None = None
    """The material next to ``x*`` (training with ``RenderConfig.albedo_smooth_sigma > 0``)."""

    def every_light(self) -> tuple[Tensor, Tensor]:
        """``(directions [R, K, 3], irradiance [R, K])`` of every light shading ``x*``: the
        emitters' :attr:`lights`, or the photon network's one light as ``K = 1``."""
        if self.lights is not None:
            return self.lights
        return self.light_dir[:, None], self.intensity[:, None]


@dataclass(frozen=True)
class SurfaceRequest:
    """Evidence beyond :class:`Surface` that a caller asks the renderer for."""

    lobe_split: bool = False
    """Fill :attr:`RenderOutput.lobe <nepf_core.render.renderer.RenderOutput.lobe>`."""
    jitter_normals: bool = False
    """Fill :attr:`MaterialSample.normal` and ``normal_mirror`` at the jittered points (the normal
    prior; a training render with a refined surface)."""

    def __or__(self, other: "SurfaceRequest") -> "SurfaceRequest":
        return SurfaceRequest(**{f.name: getattr(self, f.name) or getattr(other, f.name)
                                 for f in dataclasses.fields(self)})


def surface_at_index(sel: "ShadedSamples", flat_max: Tensor, pts: Tensor, normals: Tensor,
                     d: Tensor) -> Surface:
    """The :class:`Surface` at the max-weight samples ``flat_max [R]`` (indices into the ``P``
    flattened samples) from the shaded samples ``sel`` (which always include them)."""
    pos = torch.full((pts.shape[0],), -1, dtype=torch.long, device=pts.device)
    pos[sel.index] = torch.arange(sel.index.shape[0], device=pts.device)
    k = pos[flat_max]
    return Surface(x=pts[flat_max], normal=normals[flat_max], direction=d, light_dir=sel.light_dir[k],
                   intensity=sel.intensity[k], albedo=sel.albedo[k], roughness=sel.roughness[k],
                   metallic=sel.metallic[k], material_logits=None if sel.logits is None else sel.logits[k],
                   lights=None if sel.lights is None else (sel.lights[0][k], sel.lights[1][k]))


def refine_surface(model, o: Tensor, d: Tensor, z: Tensor, f: Tensor, idx_max: Tensor, *,
                   jitter_sigma: float = 0.0, jitter_normals: bool = False
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None, tuple[Tensor, Tensor] | None]:
    """The zero crossing ``x_r = o + t* d`` inside each ray's max-weight section
    (:func:`nepf_core.render.neus.surface_crossing_t`), its tetrahedral finite-difference normal
    and SDF features, in one SDF call. With ``jitter_sigma > 0`` the smoothness priors' points
    ``x_j = x_r + N(0, sigma^2 I)`` (``torch.randn``) join the same call; with ``jitter_normals``
    also their mirror images ``2 x_r - x_j`` and the stencils of both (the normal prior's second
    difference), which the call otherwise leaves out.

    Returns ``(x_r [R, 3], n_r [R, 3], feat_r [R, F], x_j [R, 3] or None, feat_j or None,
    (n_j, n_mirror) [R, 3] each, or None)``."""
    R = o.shape[0]
    xr = o + d * surface_crossing_t(z, f, idx_max)[:, None]
    queries = [xr]
    xj = fj = None
    jitter_normals = jitter_normals and jitter_sigma > 0
    if jitter_sigma > 0:
        eps = jitter_sigma * torch.randn(xr.shape, device=o.device, dtype=xr.dtype)
        xj = xr + eps
        queries += [xj, xr - eps] if jitter_normals else [xj]
    step = model.sdf.fd_step()
    at = torch.cat(queries, 0) if jitter_normals else xr
    stencil, offsets = fd_stencil(at, step, scheme="tetra", center="mean")
    f_all, feat_all = model.sdf(torch.cat([stencil] + queries, 0))
    g, _ = gradient_from_stencil(f_all, at.shape[0], offsets, step, scheme="tetra", center="mean")
    n = g / g.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    fr = feat_all[stencil.shape[0]:stencil.shape[0] + R]
    fj = None if xj is None else feat_all[stencil.shape[0] + R:stencil.shape[0] + 2 * R]
    nj = (n[R:2 * R], n[2 * R:]) if jitter_normals else None
    return xr, n[:R], fr, xj, fj, nj


def jittered_material(model, surface: Surface, sigma: float, *, amp: bool, xj: Tensor | None = None,
                      fj: Tensor | None = None, nj: tuple[Tensor, Tensor] | None = None) -> MaterialSample:
    """The material at ``x_j = sg(x*) + N(0, sigma^2 I)`` with the normal ``sg(n*)`` (``xj, fj``:
    points and SDF features already drawn by :func:`refine_surface`; else drawn here with
    ``torch.randn`` and one SDF call). ``nj``: the SDF normals at ``x_j`` and at its mirror image
    from :func:`refine_surface`, carried for the normal prior (None without a refined surface)."""
    if xj is None:
        x = surface.x.detach()
        xj = x + sigma * torch.randn(x.shape, device=x.device, dtype=x.dtype)
        _, fj = model.sdf(xj)
    with torch.autocast(device_type=xj.device.type, dtype=torch.bfloat16, enabled=amp and xj.device.type == "cuda"):
        a_j, r_j, m_j = model.material(xj, surface.normal.detach(), fj)
    n_j, n_m = nj if nj is not None else (None, None)
    return MaterialSample(a_j.float(), r_j.float(), m_j.float(), n_j, n_m)


@torch.no_grad()
def lobe_split(surface: Surface, rgb_surf: Tensor, *, lambertian: bool, kind: str) -> LobeSplit:
    """:class:`LobeSplit` of ``L_surf [R, 3]`` shaded at ``surface`` with the BSDF ``kind``."""
    s = surface
    dirs, irradiance = s.every_light()
    diffuse_only = sum(bsdf.shade(s.normal, dirs[:, k], -s.direction, s.albedo, s.roughness[:, None],
                                  s.metallic[:, None], irradiance[:, k, None], lambertian=lambertian,
                                  specular=False, kind=kind) for k in range(dirs.shape[1]))
    rgb = rgb_surf.detach()
    total = rgb.sum(-1)
    share = (total - diffuse_only.sum(-1)).clamp_min(0) / total.clamp_min(1e-6)
    return LobeSplit(diffuse_only=diffuse_only, share=share, absolute=(rgb - diffuse_only).clamp_min(0).mean(-1))
