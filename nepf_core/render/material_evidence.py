"""Which material a surface point is, read from how the radiance field says it looks across views.

The radiance network ``R(x, v)`` fits every training view, so at a lit surface point ``x*`` it
gives the point's colour toward each training camera that faces and sees it:
``c_k = R(x*, v_k)``, ``k = 1..K``. With the light direction ``l`` held (the photon field's, no
grad) the glTF BSDF (:mod:`nepf_core.bsdf`) makes that colour *affine in the albedo* for either
kind of material, per channel ``c``:

    c_kc = alpha_c A_k + beta B_k,        alpha_c = a_c beta,  beta = E (n . l),  0 <= a_c <= 1
    dielectric (m = 0):  A_k = (1 - F_k) / pi,        B_k = F_k D_k V_k,   F_k = 0.04 + 0.96 S_k
    metal      (m = 1):  A_k = (1 - S_k) D_k V_k,     B_k = S_k D_k V_k
    S_k = (1 - h_k . v_k)^5,  D, V: GGX and Smith at roughness r (``ggx_alpha_smooth``)

``E`` (the light's intensity) is unknown and enters only through ``beta``. For each hypothesis
``h = (m, r)`` on :data:`ROUGHNESS_GRID` x {0, 1}, :func:`fit_hypotheses` fits ``(a, beta)`` to
the views by least squares (alternating exact minimisation: ``a`` clamped to [0, 1] per channel
for fixed ``beta``, then ``beta >= 0`` for fixed ``a``) and scores it by its relative residual

    e_h = (sum_kc (fit_kc - c_kc)^2 + eps sum_kc c_kc^2) / sum_kc c_kc^2      (eps = RESIDUAL_FLOOR)

The floor stands for the radiance network's own error: two hypotheses that both fit to within it
are not told apart. The evidence (:func:`material_evidence`):

* metallic target ``m* = [e_metal < e_dielectric]`` with confidence
  ``q_m = |e_d - e_m| / max(e_d, e_m)`` (``e_d``, ``e_m``: each kind's best roughness);
* the best hypothesis's roughness ``r*`` (reported by ``bench.evidence_report``, not trained:
  docs/FAST.md).

With the light search (:func:`material_evidence`) each hypothesis is scored at the best of the
learned direction and that direction tilted by :data:`LIGHT_TILTS_DEG` at
:data:`LIGHT_AZIMUTHS` azimuths: the learned light is 15-50 degrees off on the suite, and a fit
at a misplaced light calls fewer metals.

Why this and not a prior: a dark dielectric and a metal fit one view alike, and a prior on the
metallic at its *current* value confirms itself (bench/RESULTS.md v31). Across views the two
kinds differ in ways the BSDF pins once the light is held: a metal has no view-independent floor
and its lobe carries the albedo's colour (at roughness 1 its lobe is nearly flat and the
difference is small); a dielectric's lobe is white and weak (F0 = 0.04). Each
hypothesis is judged at its own best albedo, so the evidence does not depend on the material the
network holds now.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from nepf_core import bsdf

ROUGHNESS_GRID = (0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0)
"""The roughness values each kind of material is fitted at."""
RESIDUAL_FLOOR = 0.01
"""``eps``: the relative squared error two hypotheses may both have and still be called alike
(1 %: a radiance network at ~20-30 dB on the training views)."""
FIT_ROUNDS = 8
"""Rounds of the alternating least squares of :func:`fit_hypotheses`."""
VIEWS_PER_POINT = 8
"""``K``: training cameras drawn per point (among those that face and see it)."""
POINTS_PER_STEP = 64
"""Lit foreground rays per training step whose surface point gathers evidence."""
MIN_FACING_COS = 0.2
"""A camera faces ``x*`` when ``n . (o - x*) / |o - x*|`` exceeds this (not grazing)."""
MIN_VIEWS = 3
"""Points seen by fewer cameras give no evidence (two views cannot tell a lobe from a floor)."""
OCCLUSION_POINTS = 10
"""SDF lookups on the segment from ``x*`` toward a camera that decide whether it sees ``x*``."""
OCCLUSION_START = 0.03
"""The first lookup's distance from ``x*`` (normalised units): past the surface's own band."""
LIGHT_TILTS_DEG = (15.0, 30.0)
"""The light directions tried besides the given one: tilted by these angles ..."""
LIGHT_AZIMUTHS = 6
"""... at this many azimuths about it (so ``1 + 2 x 6 = 13`` directions)."""


@dataclass
class MaterialEvidence:
    """Per point (``P``): the metallic target and its confidence in [0, 1], the best hypothesis's
    roughness, and ``residual [P, H]`` (``H = 2 len(ROUGHNESS_GRID)``, dielectrics first)."""

    metallic: Tensor
    metallic_confidence: Tensor
    roughness: Tensor
    residual: Tensor


def hypothesis_basis(n: Tensor, l: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """``(A, B)``, each ``[P, H, K]``: the affine basis of the module docstring for every
    hypothesis (dielectrics at :data:`ROUGHNESS_GRID`, then metals) at ``n, l [P, 3]`` and the
    unit directions toward the cameras ``v [P, K, 3]``. Back-facing ``l`` or ``v`` give 0."""
    r = torch.tensor(ROUGHNESS_GRID, dtype=n.dtype, device=n.device)[None, :, None]       # [1, G, 1]
    alpha = bsdf.ggx_alpha_smooth(r)
    nl = (n * l).sum(-1)[:, None, None]                                                  # [P, 1, 1]
    nv = (n[:, None, :] * v).sum(-1)[:, None, :]                                         # [P, 1, K]
    h = bsdf.half_vector(l[:, None, :], v)
    nh = (n[:, None, :] * h).sum(-1)[:, None, :].clamp(0.0, 1.0)
    hv = (0.5 * (l[:, None, :] + v).norm(dim=-1))[:, None, :].clamp(0.0, 1.0)
    front = ((nl > 0) & (nv > 0)).to(n.dtype)
    S = bsdf.schlick_weight(hv)
    DV = bsdf.ggx_distribution(nh, alpha) * bsdf.smith_visibility_gltf(nl, nv, alpha)    # [P, G, K]
    F = 0.04 + 0.96 * S
    A_die = ((1.0 - F) / math.pi).expand_as(DV)
    A = torch.cat([A_die, (1.0 - S) * DV], 1) * front
    B = torch.cat([F * DV, S * DV], 1) * front
    return A, B


def least_squares_albedo(s_aa: Tensor, s_bb: Tensor, s_ab: Tensor, s_ac: Tensor, s_bc: Tensor) -> Tensor:
    """``a [..., 3]``: the albedo ``alpha_c / beta`` of the unconstrained least squares in
    ``(alpha_c, beta)`` (the closed form of :func:`fit_hypotheses`'s docstring) from the sums
    ``S_AA, S_BB, S_AB [...]`` and ``S_Ac, S_Bc [..., 3]``, clamped to [0, 1]; 0.5 where the
    normal equations are singular (a hypothesis whose ``A`` and ``B`` are proportional)."""
    s_aa_safe = s_aa.clamp_min(1e-12)
    det = 3.0 * (s_bb - s_ab * s_ab / s_aa_safe)
    beta = ((s_bc.sum(-1) - s_ab * s_ac.sum(-1) / s_aa_safe) / det.clamp_min(1e-12)).clamp_min(1e-12)
    a = ((s_ac - beta[..., None] * s_ab[..., None]) / (beta * s_aa_safe)[..., None]).clamp(0.0, 1.0)
    return torch.where((det > 1e-12)[..., None], a, torch.full_like(a, 0.5))


def fit_hypotheses(c: Tensor, A: Tensor, B: Tensor, valid: Tensor) -> Tensor:
    """Relative residuals ``e [P, H]`` of the best ``(a, beta)`` per hypothesis (module docstring)
    for the colours ``c [P, K, 3]`` (linear), the basis ``A, B [P, H, K]`` and the views that count
    ``valid [P, K]`` (bool).

    Everything is done on the sums ``S_XY = sum_k X_k Y_k`` over the valid views (the fit's
    sufficient statistics), so the rounds cost nothing per view. The start is the unconstrained
    least squares in ``(alpha_c, beta)``, in closed form from the normal equations::

        beta    = (sum_c S_Bc - S_AB sum_c S_Ac / S_AA) / (3 (S_BB - S_AB^2 / S_AA))
        alpha_c = (S_Ac - beta S_AB) / S_AA

    exact whenever it is feasible (``0 <= a_c = alpha_c / beta <= 1``); then
    :data:`FIT_ROUNDS` rounds of exact alternating minimisation under the bounds (``a`` clamped
    per channel for fixed ``beta``, then ``beta >= 0`` for fixed ``a``), each never raising the
    residual. Where the bounds bind this can stop short of the constrained optimum (a review
    against SLSQP found 5 of 560 random cases, sharp metals whose optimum needs ``beta ~ 1e6``, a
    lobe's far tail under an absurd light), so ``e`` is an upper bound of the best residual. The
    residual is ``sum_kc (beta (a_c A_k + B_k) - c_kc)^2 = beta^2 Q - 2 beta L + S_cc`` with
    ``Q = sum_c (a_c^2 S_AA + 2 a_c S_AB + S_BB)`` and ``L = sum_c (a_c S_Ac + S_Bc)``."""
    c = c.to(A.dtype)
    w = valid.to(c.dtype)[:, None, :]                                                    # [P, 1, K]
    Aw, Bw = A * w, B * w                                                                # [P, H, K]
    s_aa, s_bb, s_ab = (Aw * Aw).sum(-1), (Bw * Bw).sum(-1), (Aw * Bw).sum(-1)           # [P, H]
    s_ac, s_bc = Aw @ c, Bw @ c                                                          # [P, H, 3]
    s_cc = (c * c * valid[..., None].to(c.dtype)).sum((1, 2))[:, None]                   # [P, 1]
    a = least_squares_albedo(s_aa, s_bb, s_ab, s_ac, s_bc)

    def quadratic_and_linear(a):
        q = (a * a * s_aa[..., None] + 2.0 * a * s_ab[..., None] + s_bb[..., None]).sum(-1)
        return q, (a * s_ac + s_bc).sum(-1)

    q, lin = quadratic_and_linear(a)
    beta = (lin / q.clamp_min(1e-12)).clamp_min(0.0)
    for _ in range(FIT_ROUNDS):
        den = (beta * s_aa)[..., None]
        a = torch.where(den > 1e-12, (s_ac - beta[..., None] * s_ab[..., None]) / den.clamp_min(1e-12), a)
        a = a.clamp(0.0, 1.0)
        q, lin = quadratic_and_linear(a)
        beta = (lin / q.clamp_min(1e-12)).clamp_min(0.0)
    sse = (beta * beta * q - 2.0 * beta * lin + s_cc).clamp_min(0.0)
    power = s_cc.clamp_min(1e-12)
    return (sse + RESIDUAL_FLOOR * power) / power


def evidence_from_residuals(e: Tensor) -> MaterialEvidence:
    """:class:`MaterialEvidence` from the residuals ``e [P, H]`` of :func:`fit_hypotheses`."""
    G = len(ROUGHNESS_GRID)
    e_die, e_met = e[:, :G], e[:, G:]
    best_die, i_die = e_die.min(1)
    best_met, i_met = e_met.min(1)
    metal = best_met < best_die
    q_m = (best_die - best_met).abs() / torch.maximum(best_die, best_met)
    grid = torch.tensor(ROUGHNESS_GRID, dtype=e.dtype, device=e.device)
    rough = grid[torch.where(metal, i_met, i_die)]
    return MaterialEvidence(metallic=metal.to(e.dtype), metallic_confidence=q_m, roughness=rough,
                            residual=e)


def light_candidates(l: Tensor) -> Tensor:
    """``[P, J, 3]``: ``l [P, 3]`` itself, then ``l`` tilted by each of :data:`LIGHT_TILTS_DEG` at
    :data:`LIGHT_AZIMUTHS` evenly spaced azimuths about it (unit vectors)."""
    helper = torch.where(l[:, :1].abs() < 0.9, l.new_tensor([1.0, 0.0, 0.0]), l.new_tensor([0.0, 1.0, 0.0]))
    t1 = torch.nn.functional.normalize(torch.cross(l, helper.expand_as(l), dim=-1), dim=-1)
    t2 = torch.cross(l, t1, dim=-1)
    out = [l]
    for tilt in LIGHT_TILTS_DEG:
        ct, st = math.cos(math.radians(tilt)), math.sin(math.radians(tilt))
        for j in range(LIGHT_AZIMUTHS):
            phi = 2.0 * math.pi * j / LIGHT_AZIMUTHS
            out.append(ct * l + st * (math.cos(phi) * t1 + math.sin(phi) * t2))
    return torch.stack(out, 1)


def material_evidence(c: Tensor, n: Tensor, l: Tensor, v: Tensor, valid: Tensor, *,
                      search_light: bool = True) -> MaterialEvidence:
    """The evidence of the module docstring at ``P`` points: colours ``c [P, K, 3]`` (linear) seen
    along the unit directions toward the cameras ``v [P, K, 3]``, unit normal ``n [P, 3]``, unit
    light direction ``l [P, 3]``, ``valid [P, K]`` the views that count. With ``search_light``
    each hypothesis is scored at the best of :func:`light_candidates` (a learned light some
    degrees off moves the highlight, and a fit at the wrong light prefers a broader lobe). No grad."""
    with torch.no_grad():
        if not search_light:
            A, B = hypothesis_basis(n, l, v)
            return evidence_from_residuals(fit_hypotheses(c, A, B, valid))
        P, K = v.shape[:2]
        ls = light_candidates(l)
        J = ls.shape[1]
        rep = lambda t: t[:, None].expand(P, J, *t.shape[1:]).reshape(P * J, *t.shape[1:])
        A, B = hypothesis_basis(rep(n), ls.reshape(P * J, 3), rep(v))
        e = fit_hypotheses(rep(c), A, B, rep(valid)).reshape(P, J, -1).min(1).values
        return evidence_from_residuals(e)


@dataclass
class EvidenceBatch:
    """The evidence of one training step: ``rays [P]`` (long, into the batch) and ``evidence``."""

    rays: Tensor
    evidence: MaterialEvidence


def _no_evidence(like: Tensor) -> MaterialEvidence:
    """Evidence at no point (a batch without a lit foreground ray: a dark start, a near-mirror)."""
    empty = like.new_zeros(0)
    return MaterialEvidence(metallic=empty, metallic_confidence=empty, roughness=empty,
                            residual=like.new_zeros(0, 2 * len(ROUGHNESS_GRID)))


@torch.no_grad()
def seen_from(sdf_fn, x: Tensor, u: Tensor) -> Tensor:
    """``[M]`` bool: the SDF is ``>= 0`` at :data:`OCCLUSION_POINTS` points evenly spaced on the
    segment from ``x + OCCLUSION_START u`` to where the ray ``x + t u`` (``u [M, 3]`` unit, toward
    the camera) leaves the unit sphere (the radiance network is trained only where a point is
    visible); ``x [M, 3]``, ``sdf_fn: [Q, 3] -> [Q]``."""
    b = (x * u).sum(-1)
    far = (-b + (b * b - (x * x).sum(-1) + 1.0).clamp_min(0.0).sqrt()).clamp_min(OCCLUSION_START)
    s = torch.linspace(0.0, 1.0, OCCLUSION_POINTS, device=x.device, dtype=x.dtype)
    t = OCCLUSION_START + (far[:, None] - OCCLUSION_START) * s[None, :]
    pts = x[:, None, :] + t[..., None] * u[:, None, :]
    return (sdf_fn(pts.reshape(-1, 3)).reshape(t.shape) >= 0.0).all(-1)


@torch.no_grad()
def views_of_points(model, x: Tensor, n: Tensor, cams: Tensor, k: int,
                    generator: torch.Generator | None) -> tuple[Tensor, Tensor, Tensor]:
    """``(c [P, k, 3], v [P, k, 3], valid [P, k])``: the radiance network's colour of each point
    ``x [P, 3]`` (unit normal ``n``, given as the network's gradient input: ``|grad f| ~ 1`` at the
    surface) seen from up to ``k`` cameras of ``cams [C, 3]`` drawn uniformly among those that
    face it, and the unit directions toward them; ``valid`` leaves out the draws that do not face
    it or do not see it (the occlusion test runs on the drawn cameras only, so a point with hidden
    cameras gets fewer than ``k``). Whether the point lies inside the camera's image is not
    checked: on the suite's orbits every facing camera frames the object."""
    P = x.shape[0]
    to_cam = cams[None, :, :] - x[:, None, :]
    to_cam = to_cam / to_cam.norm(dim=-1, keepdim=True).clamp_min(1e-8)                # [P, C, 3]
    facing = (to_cam * n[:, None, :]).sum(-1) > MIN_FACING_COS
    score = torch.rand(facing.shape, generator=generator,
                       device=generator.device if generator is not None else x.device)
    score = score.to(x.device).masked_fill(~facing, -1.0)
    top, cam = score.topk(min(k, cams.shape[0]), dim=-1)                                # [P, k]
    v = torch.gather(to_cam, 1, cam[..., None].expand(-1, -1, 3))
    xs = x[:, None, :].expand_as(v).reshape(-1, 3)
    valid = (top >= 0.0) & seen_from(model.sdf.sdf, xs, v.reshape(-1, 3)).reshape(top.shape)
    _, feat = model.sdf(x)
    kk = v.shape[1]
    c = model.radiance(xs, -v.reshape(-1, 3), n[:, None, :].expand_as(v).reshape(-1, 3),
                       feat[:, None, :].expand(P, kk, feat.shape[-1]).reshape(P * kk, -1)).float()
    return c.reshape(P, kk, 3), v, valid


def gather_evidence(model, x: Tensor, n: Tensor, light_dir: Tensor, keep: Tensor, cams: Tensor,
                    generator: torch.Generator | None = None, *, points: int = POINTS_PER_STEP,
                    k: int = VIEWS_PER_POINT) -> EvidenceBatch:
    """The evidence at up to ``points`` rays drawn among ``keep [R]`` (bool: lit foreground), at
    their surface points ``x, n, light_dir [R, 3]`` (detached here), cameras ``cams [C, 3]``
    (normalised frame). Points seen by fewer than :data:`MIN_VIEWS` cameras are left out."""
    rows = keep.nonzero(as_tuple=True)[0]
    if rows.numel() == 0:
        return EvidenceBatch(rays=rows, evidence=_no_evidence(x))
    if rows.numel() > points:
        pick = torch.randperm(rows.numel(), generator=generator)[:points].to(rows.device)
        rows = rows[pick]
    x, n, l = x.detach()[rows], n.detach()[rows], light_dir.detach()[rows]
    c, v, valid = views_of_points(model, x, n, cams.to(x), k, generator)
    enough = valid.sum(-1) >= MIN_VIEWS
    rows, c, v, valid, n, l = rows[enough], c[enough], v[enough], valid[enough], n[enough], l[enough]
    if rows.numel() == 0:
        return EvidenceBatch(rays=rows, evidence=_no_evidence(x))
    return EvidenceBatch(rays=rows, evidence=material_evidence(c, n, l, v, valid))
