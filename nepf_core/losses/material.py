"""The material priors (all off in ``paper``): smoothness, the lobe-off albedo flatness, the logit
range, and the metal terms.

    L_asm    = w_albedo_smooth * mean_surf | c(x*) - c(x* + e) |
    L_flat   = w_albedo_flat * mean_lit | Y(c) / sg(mean_lit Y(c)) - 1 |, Y = channel mean  (lobe off only)
    L_fill   = w_albedo_fill * mean_surf [shadowed] | c(x*) - sg(mean_bright c) |
               (shadowed: unlit pixel and dark under the traced emitters; bright: lit and not dark)
    L_bsm    = w_brdf_smooth * mean_surf (|r(x*) - r(x* + e)| + |m(x*) - m(x* + e)|)
    L_range  = w_material_range * mean_surf mean_k relu(|z_k| - z_max)   (z: material logits)
    L_unseen = w_metallic_unseen * mean_lit m (1 - s) (1 - share)
               (s: the lobe's share of L_surf, stop-grad; share: the metal evidence recorded near x*,
               train/metal_record.py)
    L_evid   = w_material_evidence * mean_p q_m |m(x*) - m*|
               (targets from the radiance field across views, render/material_evidence.py)

``e`` is the render's jitter of the surface point (``render.albedo_smooth_sigma``). Each reads a
:class:`~nepf_core.losses.batch.LossBatch` and returns a scalar ``[]``; why each exists is in
:class:`~nepf_core.losses.config.LossConfig`.
"""

from __future__ import annotations

from torch import Tensor

from nepf_core.fields.emitters import dark_under_emitters
from nepf_core.losses.batch import LossBatch, logit_excess, mean_where, needs_input

_JITTER = "render.albedo_smooth_sigma > 0 (a training render's Surface.jitter)"


def loss_albedo_smooth(b: LossBatch) -> Tensor:
    s = b.out.surface
    j = needs_input(s.jitter, "w_albedo_smooth", _JITTER)
    return mean_where((s.albedo - j.albedo).abs().mean(-1), b.on_surf)


def loss_albedo_flat(b: LossBatch) -> Tensor:
    if b.specular or b.lit.sum() < 2:
        return b.zero
    lum = b.out.surface.albedo[b.lit].mean(-1)
    return (lum / lum.detach().mean().clamp_min(1e-4) - 1.0).abs().mean()


def loss_albedo_fill(b: LossBatch) -> Tensor:
    s = b.out.surface
    lights = needs_input(s.lights, "w_albedo_fill", 'model.light = "emitters" (the traced emitters\' irradiance)')
    dark = dark_under_emitters(*lights, s.normal, among=b.on_surf)
    shadowed, bright = b.on_surf & ~b.lit & dark, b.lit & ~dark
    if not shadowed.any() or int(bright.sum()) < 2:
        return b.zero
    target = s.albedo[bright].detach().mean(0)
    return (s.albedo[shadowed] - target).abs().mean(-1).sum() / b.on_surf.sum()


def loss_brdf_smooth(b: LossBatch) -> Tensor:
    s = b.out.surface
    j = needs_input(s.jitter, "w_brdf_smooth", _JITTER)
    return mean_where((s.roughness - j.roughness).abs() + (s.metallic - j.metallic).abs(), b.on_surf)


def loss_material_range(b: LossBatch) -> Tensor:
    z = needs_input(b.out.surface.material_logits, "w_material_range", "a training render (material logits)")
    return mean_where(logit_excess(z, b.cfg.material_logit_max).mean(-1), b.on_surf)


def loss_metallic_unseen(b: LossBatch) -> Tensor:
    lobe = needs_input(b.out.lobe, "w_metallic_unseen", "a render with SurfaceRequest(lobe_split=True)")
    unseen = b.out.surface.metallic * (1.0 - lobe.share.detach())
    if b.out.metal_share is not None:
        unseen = unseen * (1.0 - b.out.metal_share)
    return mean_where(unseen, b.lit)


def loss_material_evidence(b: LossBatch) -> Tensor:
    eb = b.out.material_evidence
    if eb.rays.numel() == 0:
        return b.zero
    s, ev = b.out.surface, eb.evidence
    return (ev.metallic_confidence * (s.metallic[eb.rays] - ev.metallic).abs()).mean()
