"""Stage 2 of the renderer: the heads (radiance, photon, material) and the BSDF at the selected samples.

At a point ``x`` with unit normal ``n``, SDF features ``F`` and ray direction ``d``:

    R(x, d, grad f, F)                                 radiance network (L_r)
    l, I = photon(x, n, F);  c, r, m = material(x, n, F)
    pbr  = f_bsdf(l, -d, n; c, r, m) I (n . l)^+        (L_vol, L_surf)

Samples whose weight is at most ``RenderConfig.head_weight_threshold`` are not shaded (they
contribute at most that weight each to any colour); each ray's max-weight sample always is.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nepf_core import bsdf
from nepf_core.fields.emitters import dark_under_emitters, dominant


@dataclass(frozen=True)
class Shading:
    """The shading model in effect (a run's switches, :class:`nepf_core.train.run_state.RunState`).

    ``specular``: evaluate the GGX lobe, ``f = f_d + f_s`` (Disney diffuse, :mod:`nepf_core.bsdf`).
    Without it the surface is shaded as ``(1 - w m) f_d(c) + w f_s`` with
    ``w = diffuse_metal_weight`` (:func:`nepf_core.bsdf.shade_fading_lobe`): 0 is a dielectric
    diffuse (metallic ignored, no lobe evaluated); adaptivity fades ``w`` from 1 to 0 after
    dropping the lobe, so the image does not jump from the full BSDF to ``f_d``."""

    specular: bool = True
    diffuse_metal_weight: float = 0.0


@dataclass
class PointShading:
    """The heads and the BSDF at ``N`` points (fp32): ``pbr [N, 3]``, ``light_dir [N, 3]``,
    ``intensity [N]``, ``albedo [N, 3]``, ``roughness [N]``, ``metallic [N]``, and in training
    the material network's raw outputs ``logits [N, 5]`` (else None)."""

    pbr: Tensor
    light_dir: Tensor
    intensity: Tensor
    albedo: Tensor
    roughness: Tensor
    metallic: Tensor
    logits: Tensor | None
    lights: tuple[Tensor, Tensor] | None = None
    """With global emitters: every emitter's ``(directions [N, K, 3], irradiance [N, K])``
    (``light_dir`` and ``intensity`` are the dominant one's); None with the photon network."""


@dataclass
class ShadedSamples(PointShading):
    """:class:`PointShading` of the selected samples plus ``index [N]`` (into the ``P`` flattened
    samples), the radiance ``radiance [N, 3]`` and, in training, its logits ``radiance_logits [N, 3]``."""

    index: Tensor = None
    radiance: Tensor = None
    radiance_logits: Tensor | None = None


def _autocast(cfg, device: torch.device):
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16,
                          enabled=cfg.amp_heads and device.type == "cuda")


def shade_points(model, cfg, shading: Shading, xs: Tensor, vs: Tensor, ns: Tensor, fs: Tensor,
                 unlit: Tensor | None, *, logits: bool = False, visibility: Tensor | None = None) -> PointShading:
    """Photon + material heads and the BSDF at ``N`` points: ``xs, vs, ns [N, 3]`` (position,
    ray direction, unit normal), ``fs [N, F]`` SDF features, ``unlit [N]`` bool or None. With
    ``cfg.unlit_albedo_stopgrad`` the colour error of an unlit point does not reach its albedo
    (a pixel that received no light says nothing about the albedo). Without
    ``shading.specular`` the fading lobe :func:`nepf_core.bsdf.shade_fading_lobe`. With global
    emitters (:mod:`nepf_core.fields.emitters`) one BSDF term per emitter is summed, each
    scaled by ``visibility [N, K]`` (None: all seen), and where that visibility is traced a dark
    pixel counts as unlit only if its point is dark under the emitters too
    (:func:`~nepf_core.fields.emitters.dark_under_emitters`): the pixel alone cannot tell a black
    texture from a shadow, the traced shadows can (docs/FAST.md, "The light model")."""
    with _autocast(cfg, xs.device):
        if logits:
            albedo, rough, metal, z = model.material(xs, ns, fs, with_logits=True)
        else:
            (albedo, rough, metal), z = model.material(xs, ns, fs), None
    if hasattr(model.photon, "illuminate"):
        dirs, irradiance = model.photon.illuminate(xs, ns, fs, visibility)
    else:
        with _autocast(cfg, xs.device):
            light_dir, intensity = model.photon(xs, ns, fs)
        dirs, irradiance = light_dir.float()[:, None], intensity.float()[:, None]
    albedo, rough, metal = albedo.float(), rough.float(), metal.float()
    albedo_shade = albedo
    if cfg.unlit_albedo_stopgrad and unlit is not None:
        if visibility is not None:
            unlit = unlit & dark_under_emitters(dirs, irradiance, ns)
        albedo_shade = torch.where(unlit[:, None], albedo.detach(), albedo)
    pbr = sum(shade_one_light(cfg, shading, ns, dirs[:, k], -vs, albedo_shade, rough, metal, irradiance[:, k])
              for k in range(dirs.shape[1]))
    light_dir, intensity = dominant(dirs, irradiance, ns)
    return PointShading(pbr, light_dir, intensity, albedo, rough, metal, None if z is None else z.float(),
                        (dirs, irradiance) if hasattr(model.photon, "illuminate") else None)


def shade_one_light(cfg, shading: Shading, n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, rough: Tensor,
                    metal: Tensor, irradiance: Tensor) -> Tensor:
    """``f(l, v, n) E (n . l)^+ [N, 3]`` for one light per point (``n, l, v [N, 3]``, ``E [N]``);
    without ``shading.specular`` the fading lobe ``(1 - w m) f_d(c) + w f_s`` (w fading to 0, a
    dielectric diffuse)."""
    if not shading.specular:
        return bsdf.shade_fading_lobe(n, l, v, albedo, rough[:, None], metal[:, None], irradiance[:, None],
                                      shading.diffuse_metal_weight, lambertian=cfg.lambertian, kind=cfg.bsdf_kind)
    return bsdf.shade(n, l, v, albedo, rough[:, None], metal[:, None], irradiance[:, None],
                      lambertian=cfg.lambertian, specular=True, kind=cfg.bsdf_kind)


def selected_samples(weights: Tensor, flat_max: Tensor, threshold: float) -> Tensor:
    """``[N]`` long: the flattened samples that get heads, ``w_i > threshold`` and each ray's
    max-weight sample ``flat_max [R]`` (every sample when ``threshold`` is 0)."""
    if threshold > 0:
        sel = weights.reshape(-1).detach() > threshold
        sel[flat_max] = True  # the surface sample is always shaded
        return sel.nonzero(as_tuple=True)[0]
    return torch.arange(weights.numel(), device=weights.device)


def shade_samples(model, cfg, shading: Shading, sw, normals: Tensor, sel_idx: Tensor,
                  unlit_ray: Tensor | None, *, train: bool, ray_visibility: Tensor | None = None) -> ShadedSamples:
    """Radiance, photon, material and the BSDF at the samples ``sel_idx`` of
    :class:`~nepf_core.render.weights.SampleWeights` ``sw`` (``normals [P, 3]`` unit;
    ``unlit_ray [R]`` or None)."""
    S = sw.weights.shape[1]
    xs, vs, ns, gs, fs = sw.pts[sel_idx], sw.dirs[sel_idx], normals[sel_idx], sw.grad[sel_idx], sw.feat[sel_idx]
    with _autocast(cfg, xs.device):
        rad, rad_z = model.radiance(xs, vs, gs, fs, with_logits=True)
    unlit = unlit_ray[sel_idx // S] if unlit_ray is not None else None
    vis = ray_visibility[sel_idx // S] if ray_visibility is not None else None
    p = shade_points(model, cfg, shading, xs, vs, ns, fs, unlit, logits=train, visibility=vis)
    return ShadedSamples(p.pbr, p.light_dir, p.intensity, p.albedo, p.roughness, p.metallic, p.logits, p.lights,
                         index=sel_idx, radiance=rad.float(), radiance_logits=rad_z.float() if train else None)
