"""The material evidence under a scene's true lights: does the one-light fit miss metals a second
light reaches (``python -m bench.evidence_report RUN SCENE --true-lights``)?

The evidence (:mod:`nepf_core.render.material_evidence`) fits each point's colours across views
with one light. A scene lit by a key and a fill shows a metal's second lobe, which a one-light
metal cannot make and which reads as the view-independent floor only a dielectric has. This
module scores the same points with the true light directions from ``SCENE/gt/lights.json``:

* **learned light**: the training's evidence (the run's light, with its tilt search), for the
  fill split;
* **key**: the one-light evidence at the direction toward the strongest light (with the same
  tilt search), and **key, two-light solver**: the key alone through :func:`fit_two_lights` with
  the second light's basis zero and no tilts, the row "all lights" is to be read against (its
  solver, three starts and more rounds, can fit lower than the training's, so the difference
  between these two rows is the second light's alone);
* **all lights** (scenes with two): each hypothesis fitted as the sum of two lights, each with its
  own ``beta_j = E_j (n . l_j) >= 0``, the fit still affine in the albedo per channel ``c``::

      c_kc = beta_1 (a_c A1_k + B1_k) + beta_2 (a_c A2_k + B2_k),     0 <= a_c <= 1

  (``A_j, B_j``: :func:`~nepf_core.render.material_evidence.hypothesis_basis` at light ``j``),
  solved by exact alternating minimisation (:func:`fit_two_lights`);

and splits the metals' call rate by the **fill share**, the other lights' part of the point's
irradiance ``E_j = I_j max(n . u_j, 0) / d_j^2`` (true normals, no shadows). The true directions
make "all lights" an upper bound for any searched second light (bench/RESULTS.md v46).

``--searched-fill`` asks what a run could get without knowing the fill: the second light's
direction searched per hypothesis over :data:`FILL_CANDIDATES` directions spread over the sphere
(:func:`fill_candidates`), with the key the learned light or the true one (:func:`searched_fill_rows`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

FILL_SHARE_BINS = ((0.0, 0.1), (0.1, 0.3), (0.3, 1.0001))
"""The fill-share bins the metals' call rate is split by."""
FIT_ROUNDS = 12
"""Rounds of :func:`fit_two_lights`'s alternating minimisation."""
FILL_CANDIDATES = 32
"""Directions the searched second light is chosen from (:func:`fill_candidates`)."""


def _nnls_two(g11: Tensor, g22: Tensor, g12: Tensor, y1: Tensor, y2: Tensor) -> tuple[Tensor, Tensor]:
    """``argmin_{b >= 0} b^T G b - 2 b^T y`` for the 2 x 2 Gram matrices ``G`` (elementwise over
    any batch shape): the unconstrained solution where both are >= 0, else the better of the two
    one-variable solutions (the optimum of a convex quadratic on the quadrant lies on a face)."""
    det = g11 * g22 - g12 * g12
    x1 = (g22 * y1 - g12 * y2) / det.clamp_min(1e-30)
    x2 = (g11 * y2 - g12 * y1) / det.clamp_min(1e-30)
    s1, s2 = (y1 / g11.clamp_min(1e-30)).clamp_min(0.0), (y2 / g22.clamp_min(1e-30)).clamp_min(0.0)
    obj = lambda p, q: p * p * g11 + q * q * g22 + 2.0 * p * q * g12 - 2.0 * p * y1 - 2.0 * q * y2
    interior = (x1 >= 0) & (x2 >= 0) & (det > 1e-30)
    zero = torch.zeros_like(s1)
    cand = torch.stack([torch.where(interior, obj(x1, x2), torch.full_like(x1, float("inf"))),
                        obj(s1, zero), obj(zero, s2)])
    pick = cand.argmin(0)
    b1 = torch.where(pick == 0, x1, torch.where(pick == 1, s1, zero))
    b2 = torch.where(pick == 0, x2, torch.where(pick == 2, s2, zero))
    return b1, b2


def _one_light_albedo(c: Tensor, w: Tensor, A: Tensor, B: Tensor) -> Tensor:
    """``a [P, H, 1, 3]``: the start of the one-light fit,
    :func:`~nepf_core.render.material_evidence.least_squares_albedo` of light ``A, B``, for the
    layout of :func:`fit_two_lights` (``c [P, 1, K, 3]``, ``w [P, 1, K, 1]``, ``A, B [P, H, K, 1]``)."""
    from nepf_core.render.material_evidence import least_squares_albedo

    Aw, Bw = A * w, B * w
    sums = ((Aw * Aw).sum((-1, -2)), (Bw * Bw).sum((-1, -2)), (Aw * Bw).sum((-1, -2)),
            (Aw * c).sum(-2), (Bw * c).sum(-2))
    return least_squares_albedo(*sums)[..., None, :]


def _betas(c: Tensor, w: Tensor, A1: Tensor, B1: Tensor, A2: Tensor, B2: Tensor, a: Tensor):
    """``(G1, G2, b1, b2)``: each light's weighted shading ``G_j = (a A_j + B_j) w`` at the albedo
    ``a`` and the betas that fit it best (:func:`_nnls_two`)."""
    G1, G2 = (a * A1 + B1) * w, (a * A2 + B2) * w
    b1, b2 = _nnls_two((G1 * G1).sum((-1, -2)), (G2 * G2).sum((-1, -2)), (G1 * G2).sum((-1, -2)),
                       (G1 * c).sum((-1, -2)), (G2 * c).sum((-1, -2)))
    return G1, G2, b1, b2


def _alternate(c: Tensor, w: Tensor, A1: Tensor, B1: Tensor, A2: Tensor, B2: Tensor, a: Tensor) -> Tensor:
    """The squared error ``[P, H]`` after :data:`FIT_ROUNDS` rounds from the albedo ``a``: the
    betas exactly for fixed ``a`` (:func:`_betas`), then ``a`` exactly per channel for fixed
    betas (clamped; kept where both betas are 0). Never rises from round to round."""
    G1, G2, b1, b2 = _betas(c, w, A1, B1, A2, B2, a)
    for _ in range(FIT_ROUNDS):
        U = (b1[..., None, None] * A1 + b2[..., None, None] * A2) * w
        W = (b1[..., None, None] * B1 + b2[..., None, None] * B2) * w
        uu = (U * U).sum(-2, keepdim=True)
        a = torch.where(uu > 1e-30, ((U * (c * w - W)).sum(-2, keepdim=True) / uu.clamp_min(1e-30)).clamp(0.0, 1.0), a)
        G1, G2, b1, b2 = _betas(c, w, A1, B1, A2, B2, a)
    fit = b1[..., None, None] * G1 + b2[..., None, None] * G2
    return ((fit - c * w) ** 2).sum((-1, -2))


def fit_two_lights(c: Tensor, A1: Tensor, B1: Tensor, A2: Tensor, B2: Tensor, valid: Tensor) -> Tensor:
    """Relative residuals ``e [P, H]`` of the two-light model of the module docstring, scored as
    :func:`~nepf_core.render.material_evidence.fit_hypotheses` scores one light
    (``(sse + eps sum c^2) / sum c^2``, ``eps = RESIDUAL_FLOOR``), for the colours ``c [P, K, 3]``,
    the bases ``A_j, B_j [P, H, K]`` and ``valid [P, K]``.

    The problem is bilinear in ``(a, beta)``, so alternating minimisation (:func:`_alternate`)
    can stop at a poor point (from a grey start, a metal fitted as a dielectric stalled at 5x the
    one-light residual in the tests). It is run from three starts, the one-light least-squares
    albedo of each light and grey, and the best is kept: with light 2 switched off the model is the
    one-light one, so the result is never worse than a one-light fit from the same start. Float64."""
    from nepf_core.render.material_evidence import RESIDUAL_FLOOR

    c = c.double()[:, None]                                                  # [P, 1, K, 3]
    w = valid.double()[:, None, :, None]                                     # [P, 1, K, 1]
    A1, B1, A2, B2 = (t.double()[..., None] for t in (A1, B1, A2, B2))       # [P, H, K, 1]
    starts = (_one_light_albedo(c, w, A1, B1), _one_light_albedo(c, w, A2, B2),
              torch.full(A1.shape[:2] + (1, 3), 0.5, dtype=torch.float64))
    sse = torch.stack([_alternate(c, w, A1, B1, A2, B2, a) for a in starts]).min(0).values
    power = ((c * w) ** 2).sum((-1, -2)).clamp_min(1e-12)                    # [P, 1]
    return ((sse + RESIDUAL_FLOOR * power) / power).float()


def scene_lights(scene_dir: Path) -> list[dict]:
    """The point lights of ``SCENE/gt/lights.json``: ``position_world`` and ``intensity_rgb`` each."""
    path = Path(scene_dir) / "gt" / "lights.json"
    if not path.is_file():
        raise SystemExit(f"--true-lights needs gt/lights.json in the scene ({Path(scene_dir).name} has none)")
    lights = [li for li in json.loads(path.read_text())["lights"] if li.get("type") == "point"]
    if not 1 <= len(lights) <= 2:
        raise SystemExit(f"--true-lights: {Path(scene_dir).name} has {len(lights)} point lights; "
                         "the fit takes one or two")
    return lights


def light_geometry(x_world: np.ndarray, n_world: np.ndarray, lights: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """``(u [J, P, 3], E [J, P])``: the unit direction from each point ``x_world [P, 3]`` toward
    each light and its irradiance ``I max(n . u, 0) / d^2`` (``I``: the mean of ``intensity_rgb``;
    unit normals ``n_world [P, 3]``; no shadows)."""
    us, es = [], []
    for li in lights:
        d = np.asarray(li["position_world"], dtype=np.float64)[None] - x_world
        dist = np.linalg.norm(d, axis=-1)
        u = d / dist[:, None]
        us.append(u)
        es.append(np.mean(li["intensity_rgb"]) * np.maximum((u * n_world).sum(-1), 0.0) / dist ** 2)
    return np.stack(us), np.stack(es)


def call_rates(metal_called: np.ndarray, metal_gt: np.ndarray, fill_share: np.ndarray | None) -> dict:
    row = {"metals_called_metal": float(metal_called[metal_gt].mean()) if metal_gt.any() else None,
           "dielectrics_called_dielectric": float((~metal_called[~metal_gt]).mean()) if (~metal_gt).any() else None}
    if fill_share is not None:
        for lo, hi in FILL_SHARE_BINS:
            sel = metal_gt & (fill_share >= lo) & (fill_share < hi)
            row[f"metals_called_metal_fill_{lo:g}_{min(hi, 1):g}"] = (float(metal_called[sel].mean()) if sel.any()
                                                                      else None, int(sel.sum()))
    return row


def _true_light_directions(pts: dict, scene_dir: Path) -> tuple[list[Tensor], np.ndarray | None]:
    """``([P, 3] per light, key first, unit, normalised frame), fill share [P] or None``: the
    directions from :func:`bench.evidence_report.lit_test_points`'s points toward the scene's true
    lights, and the other lights' share of each point's irradiance (one light: None)."""
    lights = scene_lights(scene_dir)
    u_world, irr = light_geometry(pts["x_world"], pts["n_gt_world"], lights)
    key = int(np.argmax([np.mean(li["intensity_rgb"]) for li in lights]))
    order = [key] + [j for j in range(len(lights)) if j != key]
    rot = pts["rotation"]                                   # world directions -> normalised frame: R^T u
    directions = [torch.nn.functional.normalize(torch.tensor(u_world[j] @ rot, dtype=torch.float32), dim=-1)
                  for j in order]
    fill = None if len(lights) == 1 else (irr.sum(0) - irr[key]) / np.maximum(irr.sum(0), 1e-12)
    return directions, fill


def true_light_rows(pts: dict, scene_dir: Path) -> dict:
    """The rows of the module docstring for the points of
    :func:`bench.evidence_report.lit_test_points` (``pts``)."""
    from nepf_core.render.material_evidence import (evidence_from_residuals, hypothesis_basis,
                                                    material_evidence)

    directions, fill = _true_light_directions(pts, scene_dir)
    l_key = directions[0]
    c, n, v, valid = pts["c"], pts["n"], pts["v"], pts["valid"]
    metal_gt = pts["metallic_gt"] > 0.5
    rows = {}
    for name, l in (("learned_light", pts["l"]), ("key_light", l_key)):
        ev = material_evidence(c, n, l, v, valid)
        rows[name] = call_rates(ev.metallic.numpy() > 0.5, metal_gt, fill)
    if len(directions) == 2:
        A1, B1 = hypothesis_basis(n, l_key, v)
        A2, B2 = hypothesis_basis(n, directions[1], v)
        for name, (a2, b2) in (("key_light_two_light_solver", (torch.zeros_like(A2), torch.zeros_like(B2))),
                               ("all_lights", (A2, B2))):
            ev2 = evidence_from_residuals(fit_two_lights(c, A1, B1, a2, b2, valid))
            rows[name] = call_rates(ev2.metallic.numpy() > 0.5, metal_gt, fill)
    return rows


def fill_candidates(count: int = FILL_CANDIDATES) -> Tensor:
    """``[count, 3]`` unit directions spread evenly over the sphere (the Fibonacci lattice:
    ``z_i = 1 - (2 i + 1) / count``, azimuth ``i`` times the golden angle ``pi (3 - sqrt 5)``), the
    searched second light's candidates; about ``sqrt(4 pi / count)`` rad apart (36 deg at 32)."""
    i = torch.arange(count, dtype=torch.float64)
    z = 1.0 - (2.0 * i + 1.0) / count
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    s = (1.0 - z * z).sqrt()
    return torch.stack([s * phi.cos(), s * phi.sin(), z], -1).float()


def best_fill_residuals(c: Tensor, n: Tensor, key: Tensor, v: Tensor, valid: Tensor,
                        candidates: Tensor) -> Tensor:
    """``e [P, H]``: per hypothesis the best two-light residual (:func:`fit_two_lights`) over the
    second light's ``candidates [M, 3]``, the key ``key [P, 3]`` fixed; never above the one-light
    fit at the key (the second light's beta may be 0)."""
    from nepf_core.render.material_evidence import hypothesis_basis

    A1, B1 = hypothesis_basis(n, key, v)
    best = None
    for u in candidates:
        A2, B2 = hypothesis_basis(n, u.expand_as(key), v)
        e = fit_two_lights(c, A1, B1, A2, B2, valid)
        best = e if best is None else torch.minimum(best, e)
    return best


def searched_fill_rows(pts: dict, scene_dir: Path, candidates: int = FILL_CANDIDATES) -> dict:
    """The call rates with the fill searched (module docstring): for the key at the learned light
    and at the true key, the one-light fit through the two-light solver (second basis zero, no
    tilts) and the best of ``candidates`` second lights, split by the true fill share."""
    from nepf_core.render.material_evidence import evidence_from_residuals

    directions, fill = _true_light_directions(pts, scene_dir)
    c, n, v, valid = pts["c"], pts["n"], pts["v"], pts["valid"]
    metal_gt = pts["metallic_gt"] > 0.5
    no_second_light = torch.zeros(1, 3)            # a zero direction: a zero basis, the one-light fit
    rows = {}
    for name, l in (("learned_key", pts["l"]), ("true_key", directions[0])):
        for fill_name, cand in (("one_light", no_second_light), ("searched_fill", fill_candidates(candidates))):
            ev = evidence_from_residuals(best_fill_residuals(c, n, l, v, valid, cand))
            rows[f"{name}_{fill_name}"] = call_rates(ev.metallic.numpy() > 0.5, metal_gt, fill)
    return rows
