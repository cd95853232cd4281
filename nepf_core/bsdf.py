"""The NePF BSDF: Disney diffuse with retro-reflection plus a GGX specular lobe.

Every term is a pure function of tensors with broadcastable shapes ``[..., k]``.
Directions are unit vectors pointing *away* from the surface: ``l`` towards the light,
``v`` towards the camera, ``n`` the outward normal; ``h = normalize(l + v)``.

Paper (Sec. 3.3 and supplementary):
    f_d     = c/pi (1 - f_l/2)(1 - f_v/2) + f_retro
    f_retro = c/pi R (f_l + f_v + f_l f_v (R - 1)),   R = 2 r (h.v)^2
    f_l     = (1 - n.l)^5,  f_v = (1 - n.v)^5
    f_s     = F G D / (4 (n.v)(n.l))
    F       = F0 + (1 - F0)(1 - h.v)^5,   F0 = 0.04 (1 - m) + c m
    G       = G1(v) G2(l),  G1(v) = n.v / (2 [alpha + (1 - alpha) n.v])
    D       = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2),   alpha = r^2

The paper does not say how the lobes combine; we use the Disney/Mitsuba convention
``f = (1 - m) f_d + f_s`` (metals have no diffuse lobe), which is also how the
ground-truth scenes were rendered.

Clamps (all documented here, see ../shared/GUIDE.md):
    * ``alpha = max(r^2, ALPHA_MIN)`` with ``ALPHA_MIN = 1e-3`` (Mitsuba's bound): GGX D
      is a delta at alpha = 0.
    * ``(1 - h.v)`` and the Schlick weights' ``(1 - n.x)`` are clamped to [0, 1].
    * ``G / (4 n.v n.l)`` is evaluated in its cancelled form
      ``1 / (16 [alpha + (1-alpha) n.v][alpha + (1-alpha) n.l])``, which is algebraically
      identical for n.l, n.v > 0 and needs no division by a cosine, so grazing angles
      cannot blow up.
    * Back-facing ``l`` or ``v`` (n.l <= 0 or n.v <= 0) give exactly zero (a mask, not a
      clamp), so no gradient flows through the back side.
    * ``h = (l + v) / max(|l + v|, 1e-8)``: when l = -v the half vector is zero, h.v = 0.
      ``h.v`` itself is evaluated as ``|l + v| / 2`` (identical for unit l, v; symmetric and
      well-conditioned as l -> -v, where ``dot(h, v)`` loses reciprocity in float32).

Two kinds (``BSDF_KINDS``, the ``kind`` argument of :func:`bsdf_eval` / :func:`shade`):

* ``"paper"``: the form above (supplementary), the default everywhere today. Its
  ``G / (4 n.v n.l) = 1 / (16 [..][..])`` is 1/16 at normal incidence where a standard
  Smith GGX has 1/4: the lobe is about a quarter of a standard one.
* ``"gltf"``: the glTF 2.0 metallic-roughness BRDF (specification, Appendix B), what three.js
  and Blender render the exported GLB with::

      c_diff = lerp(c, 0, m),   F0 = lerp(0.04, c, m),   alpha = r^2
      F      = F0 + (1 - F0)(1 - |v.h|)^5
      f      = (1 - F) c_diff / pi  +  F D V
      D      = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)
      V      = G / (4 |n.l| |n.v|)
             = 1 / ((|n.l| + sqrt(alpha^2 + (1 - alpha^2)(n.l)^2)) (|n.v| + sqrt(alpha^2 + (1 - alpha^2)(n.v)^2)))

  ``V`` is the specification's *separable* Smith form (``G = G1(l) G1(v)``,
  ``G1(x) = 2 |n.x| / (|n.x| + sqrt(alpha^2 + (1 - alpha^2)(n.x)^2))``).
  three.js and the Khronos sample viewer use the height-correlated variant
  (:func:`smith_visibility_correlated`), equal at normal incidence. The only departure from
  the specification is the roughness floor: ``alpha = ALPHA_MIN + (1 - ALPHA_MIN) r^2``
  (:func:`ggx_alpha_smooth`) instead of ``alpha = r^2`` (a delta at r = 0) or the paper
  path's ``max(r^2, ALPHA_MIN)``, whose gradient in r is exactly 0 below r ~ 0.03 (a
  near-mirror fit cannot move). The smooth floor keeps ``d alpha / d r = 2 (1 - ALPHA_MIN) r``
  non-zero for every r > 0 and differs from ``r^2`` by at most ``ALPHA_MIN``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

ALPHA_MIN = 1e-3
HALF_EPS = 1e-8


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Row-wise dot product: ``[..., 3] x [..., 3] -> [..., 1]``."""
    return (a * b).sum(dim=-1, keepdim=True)


def half_vector(l: Tensor, v: Tensor) -> Tensor:
    """``h = (l + v) / max(|l + v|, 1e-8)``; shapes ``[..., 3] -> [..., 3]``."""
    s = l + v
    return s / s.norm(dim=-1, keepdim=True).clamp_min(HALF_EPS)


def ggx_alpha(roughness: Tensor) -> Tensor:
    """``alpha = max(r^2, ALPHA_MIN)``; ``[..., 1] -> [..., 1]``."""
    return (roughness * roughness).clamp_min(ALPHA_MIN)


def schlick_weight(cos: Tensor) -> Tensor:
    """``(1 - cos)^5`` with ``1 - cos`` clamped to [0, 1]; ``[..., 1] -> [..., 1]``."""
    return (1.0 - cos).clamp(0.0, 1.0) ** 5


def retro_reflection(albedo: Tensor, roughness: Tensor, f_l: Tensor, f_v: Tensor, hv: Tensor) -> Tensor:
    """``f_retro = c/pi R (f_l + f_v + f_l f_v (R - 1))`` with ``R = 2 r (h.v)^2``.

    Shapes: albedo ``[..., 3]``, others ``[..., 1]`` -> ``[..., 3]``.
    """
    R = 2.0 * roughness * hv * hv
    return albedo / math.pi * R * (f_l + f_v + f_l * f_v * (R - 1.0))


def disney_diffuse(albedo: Tensor, roughness: Tensor, nl: Tensor, nv: Tensor, hv: Tensor) -> Tensor:
    """``f_d = c/pi (1 - f_l/2)(1 - f_v/2) + f_retro`` (front-facing cosines assumed).

    Shapes: albedo ``[..., 3]``, roughness/nl/nv/hv ``[..., 1]`` -> ``[..., 3]``.
    Worked value: c = 1, r = 0, n.l = n.v = 1 gives f_l = f_v = 0 and f_d = 1/pi.
    """
    f_l = schlick_weight(nl)
    f_v = schlick_weight(nv)
    base = albedo / math.pi * (1.0 - 0.5 * f_l) * (1.0 - 0.5 * f_v)
    return base + retro_reflection(albedo, roughness, f_l, f_v, hv)


def lambert_diffuse(albedo: Tensor) -> Tensor:
    """``f_d = c / pi`` (the paper's BRDF ablation); ``[..., 3] -> [..., 3]``."""
    return albedo / math.pi


def fresnel_f0(albedo: Tensor, metallic: Tensor) -> Tensor:
    """``F0 = 0.04 (1 - m) + c m``; ``[..., 3], [..., 1] -> [..., 3]``."""
    return 0.04 * (1.0 - metallic) + albedo * metallic


def fresnel_schlick(f0: Tensor, hv: Tensor) -> Tensor:
    """``F = F0 + (1 - F0)(1 - h.v)^5``, ``(1 - h.v)`` clamped to [0, 1]."""
    return f0 + (1.0 - f0) * schlick_weight(hv)


def geometry_g1(cos: Tensor, alpha: Tensor) -> Tensor:
    """Paper's ``G1(x) = n.x / (2 [alpha + (1 - alpha) n.x])`` for ``n.x >= 0``.

    Worked value: alpha = 1 gives n.x / 2.
    """
    c = cos.clamp_min(0.0)
    return c / (2.0 * (alpha + (1.0 - alpha) * c))


def geometry_smith(nl: Tensor, nv: Tensor, alpha: Tensor) -> Tensor:
    """``G(l, v) = G1(v) G2(l)`` (G2 has the same form as G1)."""
    return geometry_g1(nv, alpha) * geometry_g1(nl, alpha)


def specular_visibility(nl: Tensor, nv: Tensor, alpha: Tensor) -> Tensor:
    """``G / (4 n.v n.l)`` in cancelled form: ``1 / (16 [a + (1-a) n.v][a + (1-a) n.l])``.

    Bounded by ``1 / (16 alpha^2)`` for all non-negative cosines.
    """
    nl = nl.clamp_min(0.0)
    nv = nv.clamp_min(0.0)
    return 1.0 / (16.0 * (alpha + (1.0 - alpha) * nv) * (alpha + (1.0 - alpha) * nl))


def ggx_distribution(nh: Tensor, alpha: Tensor) -> Tensor:
    """``D(h) = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)``; ``[..., 1] -> [..., 1]``.

    Worked value: n.h = 1 gives ``1 / (pi alpha^2)``.
    """
    a2 = alpha * alpha
    nh = nh.clamp(0.0, 1.0)
    denom = nh * nh * (a2 - 1.0) + 1.0
    return a2 / (math.pi * denom * denom)


def ggx_specular(albedo: Tensor, roughness: Tensor, metallic: Tensor,
                 nl: Tensor, nv: Tensor, nh: Tensor, hv: Tensor) -> Tensor:
    """``f_s = F G D / (4 n.v n.l)`` (front-facing cosines assumed); -> ``[..., 3]``."""
    alpha = ggx_alpha(roughness)
    F = fresnel_schlick(fresnel_f0(albedo, metallic), hv)
    return F * ggx_distribution(nh, alpha) * specular_visibility(nl, nv, alpha)


BSDF_KINDS = ("paper", "gltf")
"""The BSDF forms :func:`bsdf_eval` can evaluate (see the module docstring)."""


def ggx_alpha_smooth(roughness: Tensor) -> Tensor:
    """``alpha = ALPHA_MIN + (1 - ALPHA_MIN) r^2``: glTF's ``r^2`` with a floor whose
    gradient ``2 (1 - ALPHA_MIN) r`` stays non-zero for r > 0; ``[..., 1] -> [..., 1]``.

    Worked values: r = 0 -> 1e-3, r = 1 -> 1, r = 0.5 -> 0.25075."""
    return ALPHA_MIN + (1.0 - ALPHA_MIN) * roughness * roughness


def smith_g1_gltf(cos: Tensor, alpha: Tensor) -> Tensor:
    """glTF's ``G1(x) = 2 |n.x| / (|n.x| + sqrt(alpha^2 + (1 - alpha^2)(n.x)^2))`` (n.x >= 0).

    Worked values: n.x = 1 -> 1 for every alpha; alpha = 1 -> 2 n.x / (n.x + 1)."""
    c = cos.clamp_min(0.0)
    a2 = alpha * alpha
    return 2.0 * c / (c + torch.sqrt(a2 + (1.0 - a2) * c * c))


def smith_visibility_gltf(nl: Tensor, nv: Tensor, alpha: Tensor) -> Tensor:
    """``V = G1(l) G1(v) / (4 n.l n.v)`` of the glTF specification, in its cancelled form
    ``1 / ((n.l + sqrt(a^2 + (1 - a^2) n.l^2)) (n.v + sqrt(a^2 + (1 - a^2) n.v^2)))``
    (no division by a cosine; at most ``1 / alpha^2``). Worked value: n.l = n.v = 1 -> 1/4."""
    nl = nl.clamp_min(0.0)
    nv = nv.clamp_min(0.0)
    a2 = alpha * alpha
    return 1.0 / ((nl + torch.sqrt(a2 + (1.0 - a2) * nl * nl)) * (nv + torch.sqrt(a2 + (1.0 - a2) * nv * nv)))


def smith_visibility_correlated(nl: Tensor, nv: Tensor, alpha: Tensor) -> Tensor:
    """Height-correlated Smith visibility (three.js, Filament, the Khronos sample viewer):
    ``V = 0.5 / (n.l sqrt(n.v^2 (1 - a^2) + a^2) + n.v sqrt(n.l^2 (1 - a^2) + a^2))``.
    Equal to :func:`smith_visibility_gltf` at n.l = n.v = 1 (1/4). Not used by a kind; kept
    to state the difference from what three.js renders (tests/test_bsdf_gltf.py)."""
    nl = nl.clamp_min(0.0)
    nv = nv.clamp_min(0.0)
    a2 = alpha * alpha
    den = nl * torch.sqrt(nv * nv * (1.0 - a2) + a2) + nv * torch.sqrt(nl * nl * (1.0 - a2) + a2)
    return 0.5 / den.clamp_min(1e-12)


def gltf_diffuse(albedo: Tensor, metallic: Tensor, fresnel: Tensor) -> Tensor:
    """``(1 - F) c_diff / pi`` with ``c_diff = (1 - m) c``; ``[..., 3], [..., 1], [..., 3] -> [..., 3]``.

    Worked value: c = 1, m = 0, F = 0.04 -> 0.96 / pi."""
    return (1.0 - fresnel) * (1.0 - metallic) * albedo / math.pi


def gltf_specular(fresnel: Tensor, nl: Tensor, nv: Tensor, nh: Tensor, alpha: Tensor) -> Tensor:
    """``F D V`` (glTF, ``V`` separable Smith); -> ``[..., 3]``. Worked value at
    n.l = n.v = n.h = 1: ``F / (4 pi alpha^2)``."""
    return fresnel * ggx_distribution(nh, alpha) * smith_visibility_gltf(nl, nv, alpha)


def _gltf_eval(n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, roughness: Tensor, metallic: Tensor,
               nl_c: Tensor, nv_c: Tensor, hv: Tensor, specular: bool) -> Tensor:
    """The glTF BRDF at front-facing cosines (see :func:`bsdf_eval`). Without ``specular``
    the lobe is dropped and the diffuse keeps its full weight: ``f = c_diff / pi``."""
    if not specular:
        return (1.0 - metallic) * lambert_diffuse(albedo)
    F = fresnel_schlick(fresnel_f0(albedo, metallic), hv)
    alpha = ggx_alpha_smooth(roughness)
    nh = dot(n, half_vector(l, v)).clamp(0.0, 1.0)
    return gltf_diffuse(albedo, metallic, F) + gltf_specular(F, nl_c, nv_c, nh, alpha)


def bsdf_eval(n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, roughness: Tensor, metallic: Tensor,
              *, lambertian: bool = False, specular: bool = True, kind: str = "paper") -> Tensor:
    """Full BSDF ``f = (1 - m) f_d + f_s``, zero when ``l`` or ``v`` is below the surface.

    Args:
        n, l, v: ``[..., 3]`` unit vectors.
        albedo: ``[..., 3]`` in [0, 1]; roughness, metallic: ``[..., 1]`` in [0, 1].
        lambertian: use ``c/pi`` instead of the Disney diffuse (ablation).
        specular: include the GGX lobe (``False`` drops it for diffuse scenes).
        kind: ``"paper"`` (Disney / Lambert diffuse + the supplementary's GGX) or ``"gltf"``
            (glTF Appendix B: ``(1 - F) c_diff / pi + F D V``; ``lambertian`` is implied).
    Returns:
        ``[..., 3]`` BSDF value (1/sr), finite and non-negative for all unit inputs.
    """
    nl = dot(n, l)
    nv = dot(n, v)
    front = ((nl > 0) & (nv > 0)).to(albedo.dtype)
    nl_c = nl.clamp(0.0, 1.0)
    nv_c = nv.clamp(0.0, 1.0)
    h = half_vector(l, v)
    # h.v = (1 + l.v) / |l + v| = |l + v| / 2 for unit l, v. The norm form is used because
    # dot(h, v) is ill-conditioned when l ~ -v: float32 inputs are unit only to ~1e-7, so
    # dot(h, v) - dot(h, l) = (|v|^2 - |l|^2) / |l + v| can reach O(0.1) with the wrong
    # sign, breaking reciprocity (f(l, v) != f(v, l)) in F and f_retro. |l + v| / 2 is
    # symmetric in (l, v) bit for bit and has bounded gradient.
    hv = (0.5 * (l + v).norm(dim=-1, keepdim=True)).clamp(0.0, 1.0)
    if kind == "gltf":
        return _gltf_eval(n, l, v, albedo, roughness, metallic, nl_c, nv_c, hv, specular) * front
    if kind != "paper":
        raise ValueError(f"unknown BSDF kind {kind!r} (one of {', '.join(BSDF_KINDS)})")
    if lambertian:
        f_d = lambert_diffuse(albedo)
    else:
        f_d = disney_diffuse(albedo, roughness, nl_c, nv_c, hv)
    f = (1.0 - metallic) * f_d
    if specular:
        nh = dot(n, h).clamp(0.0, 1.0)
        f = f + ggx_specular(albedo, roughness, metallic, nl_c, nv_c, nh, hv)
    return f * front


def shade(n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, roughness: Tensor, metallic: Tensor,
          intensity: Tensor, *, lambertian: bool = False, specular: bool = True, kind: str = "paper") -> Tensor:
    """Outgoing radiance from one light: ``L = f(l, v) * I * max(n.l, 0)``.

    Shapes: as :func:`bsdf_eval`, ``intensity`` ``[..., 1]`` (or ``[..., 3]``) -> ``[..., 3]``.
    """
    f = bsdf_eval(n, l, v, albedo, roughness, metallic, lambertian=lambertian, specular=specular, kind=kind)
    return f * intensity * dot(n, l).clamp_min(0.0)


def shade_fading_lobe(n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, roughness: Tensor, metallic: Tensor,
                      intensity: Tensor, weight: float, *, lambertian: bool = False, kind: str = "paper") -> Tensor:
    """Shading while a dropped GGX lobe fades out:
    ``L = ((1 - w m) f_d(c) + w f_s(c, r, m)) * I * max(n.l, 0)``.

    ``w = 1`` is the full BSDF (the image just before the drop), ``w = 0`` a dielectric diffuse
    (metallic ignored). ``f_d`` does not depend on ``m``, so this is the blend
    ``(1 - w) f(m = 0, no lobe) + w f(m)`` of the two end points: linear in ``w``, the image
    changes by a bounded amount per step while ``w`` goes from 1 to 0. Shapes: as :func:`shade`.
    """
    f = bsdf_eval(n, l, v, albedo, roughness, torch.zeros_like(metallic), lambertian=lambertian, specular=False,
                  kind=kind)
    if weight > 0.0:
        f_full = bsdf_eval(n, l, v, albedo, roughness, metallic, lambertian=lambertian, specular=True, kind=kind)
        f = (1.0 - weight) * f + weight * f_full
    return f * intensity * dot(n, l).clamp_min(0.0)


def diffuse_only_material(albedo: Tensor, roughness: Tensor, metallic: Tensor,
                          weight: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """The material rendered once the GGX lobe is dropped: ``(c, r, m) -> ((1 - w m) c, 1, 0)``.

    With the lobe off the renderer shades ``f = (1 - w m) f_d(c)``
    (``RenderConfig.diffuse_metal_weight = w``), and both diffuse models are linear in the
    albedo, so ``(1 - w m) f_d(c) = f_d((1 - w m) c)``: the returned triple renders the same
    diffuse with metallic 0, which is what an exported asset must carry (a renderer such as
    Blender would otherwise add a metallic lobe the fit never had). ``w`` fades from 1 to 0
    after the drop (:func:`shade_fading_lobe`; the fading lobe ``w f_s`` itself is not carried,
    so an asset exported mid-fade lacks it); at 0 the surface is a dielectric diffuse and ``m``
    is ignored. Keeping ``w = 1``
    leaves ``m`` as a free per-point dimmer that trades against the albedo and the photon
    intensity: measured on sphere_diffuse, held-out PBR 46.0 dB but aligned albedo PSNR 6.7 dB
    (red albedo saturated at 1, metallic spread over [0, 1]).

    The roughness becomes ``DROPPED_LOBE_ROUGHNESS``: a glTF dielectric always has its
    ``F0 = 0.04`` lobe, and the roughness the network held at the drop stops learning there (it
    no longer shades anything), so a value frozen low would draw needle highlights the fit never
    had (sphere_diffuse with global emitters: roughness 0.05 at the drop, bench/RESULTS.md v56);
    the widest lobe is the nearest glTF has to "no lobe". (The ``paper`` BSDF's Disney diffuse
    reads the roughness, so ``nepf relight``, which shades a lobe-dropped run with its own BSDF
    and no lobe, keeps the network's; an exported asset is shaded with the glTF BSDF, whose
    diffuse does not read it.)
    Shapes: ``albedo [..., 3]``, ``roughness`` and ``metallic [...]`` or ``[..., 1]`` -> same shapes.
    """
    m = metallic if metallic.dim() == albedo.dim() else metallic[..., None]
    return albedo * (1.0 - weight * m), torch.full_like(roughness, DROPPED_LOBE_ROUGHNESS), torch.zeros_like(metallic)


DROPPED_LOBE_ROUGHNESS = 1.0
"""The roughness a lobe-dropped surface carries (:func:`diffuse_only_material`)."""
