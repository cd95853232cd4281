"""The loss weights: :class:`LossConfig`, what the user asks of each term (0 switches it off)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class LossConfig:
    """Loss weights (0 switches a term off). Defaults are the paper's where it gives them."""

    w_r: float = 1.0
    """Outgoing-radiance colour loss."""
    lambda1_surf: float = 3e-4
    """Paper lambda1 (L_surf)."""
    lambda2_vol: float = 1e-4
    """Paper lambda2 (L_vol)."""
    w_eikonal: float = 0.1
    """Eikonal weight (NeuS's value; the paper gives none)."""
    w_hessian: float = 5e-4
    """Hessian weight (the paper gives none)."""
    w_light: float = 1e-4
    """Overall light-variance weight (paper: 1e-4)."""
    lambda3: float = 1.0
    """``|var x - var I|``: the light intensity varies across the batch about as much as the
    surface points do, no more; this is what keeps a texture out of the intensity (without it,
    spot_textured's spots went into the light: docs/TRIED.md, ``w_light = 0``)."""
    lambda4: float = 1.0
    """``|var n - var l|``: the light directions spread as much as the normals. For one distant or
    point light the true spread is far smaller, so this tilts ``l`` toward ``n``, raises ``n.l`` at
    grazing points and moves the shading into the albedo (0 in ``fast``; docs/FAST.md, "The light
    field's direction terms")."""
    lambda5: float = 0.1
    """``|var x - var l|``: the directions spread as much as the points (0 in ``fast``, as ``lambda4``)."""
    w_albedo_smooth: float = 0.0
    """Albedo smoothness prior at the surface points; > 0 needs ``RenderConfig.albedo_smooth_sigma
    > 0`` (an error otherwise: :meth:`nepf_core.config.NePFConfig.check`); not in the paper. Unlit regions carry no albedo information, so without a prior
    their albedo is whatever the network extrapolates; this lets neighbouring lit albedo fill it."""
    w_albedo_flat: float = 0.0
    """Lobe off only (``compute_losses(..., specular=False)``): lit surface rays pull the
    luminance of their albedo toward the batch's mean (stop-grad), relative L1. Diffuse-only
    shading ``c I(x) (n.l) / pi`` sees only the product of the albedo and the scalar photon
    intensity, so any pattern ``s(x)`` the photon network can represent moves freely between
    them; this term gives it to the light (slow variation is illumination: the Retinex
    assumption). Both this and the colour terms are L1, so texture stays in the albedo only where
    the colour terms' gradient on the albedo is larger, and that gradient carries the shading
    ``I (n.l) / pi`` and the sRGB slope: the weight must stay well under ``lambda2_vol`` times
    that slope, or the texture moves into the light (docs/FAST.md, "What fixed it")."""
    w_albedo_fill: float = 0.0
    """Where no light reaches, the albedo of the lit surface: ``mean_surf [shadowed] |c(x*) -
    sg(mean_bright c)|`` (per channel, normalised by the surface rays), ``shadowed`` the surface
    rays whose pixel is unlit and whose point is dark under the traced emitters, ``bright`` the lit
    rays that are not (:func:`nepf_core.fields.emitters.dark_under_emitters`); needs
    ``model.light = "emitters"``. No training pixel shows such a point's albedo, but a novel light
    does: without this term the network extrapolates it from the lit side's trend, and a few
    per cent of shading left in the lit albedo along ``n . l`` (a point light's distance is weakly
    fixed by the images) becomes 5-12 % too dark an unlit half (sphere_diffuse, bench/RESULTS.md
    v56, v58). The batch's mean is the least-informed guess and says nothing about texture; the
    weight stays 10x under the smoothness prior's, because at its weight the pull flattened the
    lit texture too (spot_textured's lit albedo 16.5 -> 12.5 dB, v58)."""
    w_brdf_smooth: float = 0.0
    """The smoothness prior of ``w_albedo_smooth`` for roughness and metallic:
    ``mean (|r(x*) - r(x* + eps)| + |m(x*) - m(x* + eps)|)``. With a smoothness prior on the albedo
    alone, a texture is cheaper to carry in metallic (a ``(1 - m)`` dimmer) than in the albedo."""
    w_material_range: float = 0.0
    """Keep the material network's raw outputs (albedo, roughness, metallic logits ``z``) within
    ``|z| <= material_logit_max``: ``mean relu(|z| - z_max)`` over surface rays. A sigmoid past
    ``|z| ~ 5`` passes almost no gradient (``sigma' < 0.007``), and for roughness ``d alpha / d r =
    2 r`` vanishes at 0 as well, so a material channel that saturates early stays there whatever
    the images say later: spot_textured's roughness sat at exactly 0 and torus_glossy's at 1 and
    its blue albedo at 1 (docs/FAST.md, "Materials: saturation and the unseen lobe")."""
    material_logit_max: float = 3.0
    """``z_max`` of ``w_material_range``: sigmoid(3) = 0.953, so every channel keeps a slope of at
    least 0.045; roughness >= 0.047 still gives a near-mirror glTF lobe (alpha = 3e-3)."""
    w_colour_range: float = 0.0
    """Keep the colour logits (the radiance network's and the background's, every value a training
    render evaluated, :attr:`RenderOutput.colour_logits`) within ``|z| <= colour_logit_max``:
    ``mean relu(|z| - z_c)``. A pixel that is exactly black (a rendered background without masks) or
    white is reached by the sigmoid only at ``z = -/+ inf``, and the L1 colour loss pushes toward
    it with the same force however close it is. Adam then carries the shared network's logits far
    past any finite value (to ~-55 in 300 steps in tests/test_colour_range.py), where
    ``sigmoid' ~ e^-55``: every colour of the network is black, no pixel's error reaches it any
    more, and NeuS, trained by colour alone, lets the surface go to fog (bench/RESULTS.md
    v28). Past ``z_c`` this term's gradient is constant, so Adam brings the logits
    back at full speed. A plain sigmoid with a wider range (mip-NeRF) was tried and does not stop
    the overshoot (docs/TRIED.md)."""
    colour_logit_max: float = 9.0
    """``z_c`` of ``w_colour_range``: sigmoid(-9) = 1.2e-4 linear is sRGB 0.0016, under half of one
    8-bit level, so any colour an image can show lies inside."""
    w_metallic_unseen: float = 0.0
    """Metallic only where its lobe is seen: ``mean_lit m (1 - s)`` with ``s`` the specular lobe's
    share of the shaded surface colour (stop-grad, :attr:`RenderOutput.lobe`), over lit surface rays.
    A metal whose lobe the views never see (roughness near 0, so the highlight is a point that no
    pixel catches) only darkens its diffuse by ``(1 - m)``, which the albedo can do as well; the
    images cannot tell the two apart, and without a prior the texture goes into metallic. Where
    the lobe carries the colour (a real metal: ``s ~ 1``) the term vanishes. With the metal
    evidence on, the term is scaled by ``1 - share`` (:attr:`RenderOutput.metal_share`): it is
    lifted where the evidence recorded in the region says metal (a metal seen away from its
    highlight has ``s ~ 0`` too, and the prior alone turned every metal dielectric)."""
    w_material_evidence: float = 0.0
    """Pull the metallic at a few lit surface points per step toward what the radiance network's
    colours from other training cameras say the point is (:mod:`nepf_core.render.material_evidence`:
    the glTF BSDF fitted as a dielectric and as a metal at several roughnesses and light
    directions, each at its own best albedo), weighted by how clearly one kind fits better. Not
    in the paper (0 in ``paper``)."""
    w_surface_points: float = 0.0
    """Without masks: ``mean |f(p)|`` at the points triangulated from the images in the object
    region (:mod:`nepf_core.train.surface_points`, Geo-NeuS's sparse-point SDF loss). Not in the
    paper (its scenes have masks)."""
    w_mask: float = 0.1
    """Mask BCE weight (NeuS's value); only applied when the scene has masks."""
    w_normal_smooth: float = 0.0
    """``w mean_surf |n(x* + e) + n(x* - e) - 2 n(x*)|``, ``e ~ N(0, sigma^2 I)`` (the albedo prior's
    jitter): a second difference of the normal across the surface, which vanishes to first order on
    any smoothly curved surface (a sphere's costs ``O(sigma^2 / r^2)``) and not on bumps at the
    jitter's scale, so it smooths the grid's cell-scale noise without flattening true curvature."""
