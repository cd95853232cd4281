"""The material evidence with one interreflection bounce (``python -m bench.evidence_report RUN
SCENE --reflections``): does light from the object itself fool the metal call?

The evidence (:mod:`nepf_core.render.material_evidence`) fits each point's colours toward the
training cameras with one point light, and calls a point metal when no view-independent floor is
needed. The shared scenes are path traced (Mitsuba, ``max_depth = 5``), so a metal also mirrors
the rest of the object: in the views far from its highlight, where a one-light metal is black,
it shows the reflected object, which reads as the floor only a dielectric has. Here each
hypothesis gets a second, reflected term from the radiance field itself (NeILF++'s tie of the
incident light to the outgoing radiance):

    c_kc = beta (a_c A_k + B_k) + gamma (a_c P_k + Q_k) L_kc,       beta, gamma >= 0, 0 <= a_c <= 1
    metal:       P_k = 1 - S_k, Q_k = S_k         (Schlick with F0 = the albedo)
    dielectric:  P_k = 0,       Q_k = F_k = 0.04 + 0.96 S_k

``A, B, S``: :func:`~nepf_core.render.material_evidence.hypothesis_basis`'s; ``L_kc`` the radiance
network's colour at the first SDF hit along the mirror ray ``r_k = 2 (n . v_k) n - v_k`` (0 where
it leaves the unit ball: the scenes' background is black); ``gamma`` stands for the lobe's
integral over the mirror neighbourhood, one number per hypothesis. Both kinds get the term, so
neither is favoured; only the tint and the Fresnel differ. The fit alternates exact steps (``a``
per channel for fixed ``beta, gamma``; ``(beta, gamma)`` by a two-variable NNLS for fixed ``a``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from bench.evidence_lights import _nnls_two

FIT_ROUNDS = 12
"""Rounds of :func:`fit_with_reflection`'s alternating minimisation."""
MIRROR_OFFSET = 0.02
"""The mirror ray starts this far off the surface along its normal (normalised units)."""


@torch.no_grad()
def reflected_radiance(model, x: Tensor, n: Tensor, v: Tensor) -> Tensor:
    """``L [P, K, 3]``: the radiance network's colour at the first SDF hit along the mirror of each
    view ``v [P, K, 3]`` (unit, toward the camera) about ``n [P, 3]`` from ``x [P, 3]``, seen
    along that ray; 0 where the ray leaves the unit ball."""
    from nepf_core.model import ModelFieldQuery
    from nepf_core.relight.tracing import TraceConfig, _ray_ball, march

    P, K = v.shape[:2]
    r = 2.0 * (n[:, None, :] * v).sum(-1, keepdim=True) * n[:, None, :] - v
    r = torch.nn.functional.normalize(r, dim=-1).reshape(-1, 3)
    o = (x + MIRROR_OFFSET * n)[:, None, :].expand(P, K, 3).reshape(-1, 3)
    query = ModelFieldQuery(model)
    _, t_exit = _ray_ball(o, r, 1.0)
    hit, t = march(query.sdf, o, r, t_exit.clamp_min(0.0), TraceConfig())
    L = torch.zeros(P * K, 3)
    if hit.any():
        xh = o[hit] + t[hit, None] * r[hit]
        nh = query.normal(xh)
        _, feat = model.sdf(xh)
        L[hit] = model.radiance(xh, r[hit], nh, feat).float()
    return L.reshape(P, K, 3)


def reflection_basis(n: Tensor, l: Tensor, v: Tensor, G: int) -> tuple[Tensor, Tensor]:
    """``(P, Q)``, each ``[P, 2G, K]``: the reflected term's tint and Fresnel of the module
    docstring, dielectrics first (as :func:`~nepf_core.render.material_evidence.hypothesis_basis`)."""
    from nepf_core import bsdf

    hv = (0.5 * (l[:, None, :] + v).norm(dim=-1)).clamp(0.0, 1.0)                     # [P, K]
    S = bsdf.schlick_weight(hv)[:, None, :].expand(-1, G, -1)
    F = 0.04 + 0.96 * S
    return torch.cat([torch.zeros_like(S), 1.0 - S], 1), torch.cat([F, S], 1)


def fit_with_reflection(c: Tensor, A: Tensor, B: Tensor, Pm: Tensor, Qm: Tensor, L: Tensor,
                        valid: Tensor) -> Tensor:
    """Relative residuals ``e [P, H]`` (as :func:`~nepf_core.render.material_evidence.fit_hypotheses`,
    with its floor) of the module docstring's fit, for ``c, L [P, K, 3]``, ``A, B, Pm, Qm [P, H, K]``."""
    from nepf_core.render.material_evidence import RESIDUAL_FLOOR

    c = c.double()[:, None]                                                            # [P, 1, K, 3]
    Lr = L.double()[:, None]
    w = valid.double()[:, None, :, None]                                               # [P, 1, K, 1]
    A, B, Pm, Qm = (t.double()[..., None] for t in (A, B, Pm, Qm))                     # [P, H, K, 1]
    a = torch.full(A.shape[:2] + (1, 3), 0.5, dtype=torch.float64)                      # [P, H, 1, 3]
    beta = gamma = None
    for _ in range(FIT_ROUNDS):
        b1 = (a * A + B).expand(-1, -1, -1, 3)
        b2 = (a * Pm + Qm) * Lr
        g11, g22, g12 = ((b1 * b1 * w).sum((2, 3)), (b2 * b2 * w).sum((2, 3)), (b1 * b2 * w).sum((2, 3)))
        beta, gamma = _nnls_two(g11, g22, g12, (b1 * c * w).sum((2, 3)), (b2 * c * w).sum((2, 3)))
        u = beta[..., None, None] * A + gamma[..., None, None] * Pm * Lr
        rest = beta[..., None, None] * B + gamma[..., None, None] * Qm * Lr
        den = (u * u * w).sum(2, keepdim=True)
        a = torch.where(den > 1e-18, (u * (c - rest) * w).sum(2, keepdim=True) / den.clamp_min(1e-18), a).clamp(0.0, 1.0)
    b1 = (a * A + B).expand(-1, -1, -1, 3)
    b2 = (a * Pm + Qm) * Lr
    fit = beta[..., None, None] * b1 + gamma[..., None, None] * b2
    sse = ((fit - c) ** 2 * w).sum((2, 3))
    power = (c * c * w).sum((2, 3)).clamp_min(1e-12)
    return ((sse + RESIDUAL_FLOOR * power) / power).float()


def reflection_rows(pts: dict, model) -> dict:
    """The metals' and dielectrics' call rates at :func:`bench.evidence_report.lit_test_points`'s
    points with the learned light (no tilt search in either row, so the two differ by the
    reflected term alone): the one-light fit and the fit with the reflected term."""
    from nepf_core.render.material_evidence import ROUGHNESS_GRID, evidence_from_residuals, hypothesis_basis

    x = torch.as_tensor(pts["x_norm"], dtype=torch.float32)
    c, n, l, v, valid = pts["c"], pts["n"], pts["l"], pts["v"], pts["valid"]
    A, B = hypothesis_basis(n, l, v)
    Pm, Qm = reflection_basis(n, l, v, len(ROUGHNESS_GRID))
    L = reflected_radiance(model, x, n, v)
    zero = torch.zeros_like(L)
    metal_gt = pts["metallic_gt"] > 0.5
    rows = {"mirror_rays_hitting": float((L.abs().sum(-1) > 0)[valid].float().mean())}
    for name, Lk in (("one_light", zero), ("with_reflection", L)):
        called = evidence_from_residuals(fit_with_reflection(c, A, B, Pm, Qm, Lk, valid)).metallic.numpy() > 0.5
        rows[name] = {"metals_called_metal": float(called[metal_gt].mean()) if metal_gt.any() else None,
                      "dielectrics_called_dielectric": float((~called[~metal_gt]).mean()) if (~metal_gt).any() else None}
    return rows
