"""Numerical-stability sweep and white-furnace checks for ``nepf_core.bsdf``.

* Sweep (issue "Numerical stability"): > 10^6 float32 configurations (the training dtype)
  mixing random values with the exact edge values n.l, n.v in {0, 1e-8, 1}, l = -n,
  roughness in {0, 1e-4, 1}, metallic in {0, 1}, albedo in {0, 1}, and h.v -> 0 (l = -v or
  l ~ -v). Every term and the full BSDF (Disney / Lambert, with / without specular) must
  have finite values and finite gradients w.r.t. every input, be non-negative, reciprocal,
  and exactly zero for back-facing l or v.
* White furnace: Monte-Carlo directional albedo of the specular lobe (F0 = 1, the worst
  case) and of the diffuse lobe (c = 1), checked against closed forms worked out by hand.
"""

from __future__ import annotations

import math

import pytest
import torch

from nepf_core import bsdf

PI = math.pi
N_CONFIGS = 1 << 20          # 1,048,576 configurations ...
CHUNK = 1 << 17              # ... in 8 chunks of 131,072 (keeps memory ~ a few 100 MB)


# --------------------------------------------------------------------------------------
# Configuration generator
# --------------------------------------------------------------------------------------

def _pick(g, k, values, p_random, random_fn):
    """Per row: one of ``values`` (uniformly) with prob 1 - p_random, else random_fn()."""
    vals = torch.tensor(values, dtype=torch.float64)
    out = vals[torch.randint(len(values), (k,), generator=g)]
    rnd = torch.rand(k, generator=g, dtype=torch.float64) < p_random
    return torch.where(rnd, random_fn(k), out)


def _configs(seed: int, k: int):
    """k configurations; returns float32 tensors and the prescribed local cosines.

    Directions are built in a local frame with the normal along +z, so with n = (0,0,1)
    the dot products n.l and n.v are *exactly* the prescribed cosines (0*x + 0*y + 1*z).
    Half of the rows are then rotated to a random normal (cosines exact up to rounding).
    """
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64

    def uni(lo, hi):
        return lambda kk: lo + (hi - lo) * torch.rand(kk, generator=g, dtype=f64)

    def log_uni(lo, hi):  # tiny positive cosines, 1e-12 .. 1e-3
        return lambda kk: torch.exp(math.log(lo) + (math.log(hi) - math.log(lo))
                                    * torch.rand(kk, generator=g, dtype=f64))

    edge_cos = [0.0, 1e-8, 1.0, -1.0]      # -1.0: l = -n (straight below)
    cos_l = _pick(g, k, edge_cos, 0.5, uni(-1.0, 1.0))
    cos_v = _pick(g, k, edge_cos, 0.5, uni(-1.0, 1.0))
    tiny = torch.rand(k, generator=g) < 0.1
    cos_l = torch.where(tiny, log_uni(1e-12, 1e-3)(k), cos_l)
    tiny = torch.rand(k, generator=g) < 0.1
    cos_v = torch.where(tiny, log_uni(1e-12, 1e-3)(k), cos_v)

    phi_v = 2 * PI * torch.rand(k, generator=g, dtype=f64)
    # azimuth of l: opposite to v (h.v -> 0 when both are grazing), opposite + 1e-6,
    # equal (l = v when cosines match), or random
    mode = torch.randint(4, (k,), generator=g)
    dphi = torch.where(mode == 0, torch.full((k,), PI, dtype=f64),
                       torch.where(mode == 1, torch.full((k,), PI + 1e-6, dtype=f64),
                                   torch.where(mode == 2, torch.zeros(k, dtype=f64),
                                               2 * PI * torch.rand(k, generator=g, dtype=f64))))
    phi_l = phi_v + dphi

    def direction(c, phi):
        s = torch.sqrt((1.0 - c * c).clamp_min(0.0))
        return torch.stack([s * torch.cos(phi), s * torch.sin(phi), c], dim=-1)

    v = direction(cos_v, phi_v)
    l = direction(cos_l, phi_l)
    # exact l = -v for 5% of rows (h = 0, h.v = 0)
    anti = torch.rand(k, generator=g) < 0.05
    l = torch.where(anti[:, None], -v, l)
    cos_l = torch.where(anti, -cos_v, cos_l)
    # l = v exactly for another 5% (h = v, h.v = 1)
    same = (torch.rand(k, generator=g) < 0.05) & ~anti
    l = torch.where(same[:, None], v, l)
    cos_l = torch.where(same, cos_v, cos_l)

    n = torch.zeros(k, 3, dtype=f64)
    n[:, 2] = 1.0
    rotate = torch.rand(k, generator=g) < 0.5
    q, r = torch.linalg.qr(torch.randn(k, 3, 3, generator=g, dtype=f64))
    q = q * torch.sign(torch.diagonal(r, dim1=1, dim2=2))[:, None, :]
    q[:, :, 0] *= torch.linalg.det(q)[:, None]
    n = torch.where(rotate[:, None], q[:, :, 2], n)
    l = torch.where(rotate[:, None], torch.einsum("kij,kj->ki", q, l), l)
    v = torch.where(rotate[:, None], torch.einsum("kij,kj->ki", q, v), v)

    rough = _pick(g, k, [0.0, 1e-4, 1.0, math.sqrt(1e-3)], 0.5, uni(0.0, 1.0))
    metal = _pick(g, k, [0.0, 1.0], 0.4, uni(0.0, 1.0))
    albedo = torch.stack([_pick(g, k, [0.0, 1.0], 0.4, uni(0.0, 1.0)) for _ in range(3)], dim=-1)

    f32 = torch.float32
    return dict(n=n.to(f32), l=l.to(f32), v=v.to(f32), albedo=albedo.to(f32),
                roughness=rough[:, None].to(f32), metallic=metal[:, None].to(f32),
                exact=~rotate, cos_l=cos_l, cos_v=cos_v)


def _leaves(cfg):
    return {k: cfg[k].clone().requires_grad_(True)
            for k in ("n", "l", "v", "albedo", "roughness", "metallic")}


def _assert_finite_with_grads(name, out, inputs):
    assert torch.isfinite(out).all(), f"{name}: non-finite value"
    leaves = list(inputs.values())
    grads = torch.autograd.grad(out.sum(), leaves, allow_unused=True, retain_graph=True)
    for key, gr in zip(inputs, grads):
        if gr is not None:
            bad = ~torch.isfinite(gr)
            assert not bad.any(), f"{name}: non-finite d/d{key} in {int(bad.sum())} rows"
    return grads


# --------------------------------------------------------------------------------------
# 4. Stability sweep
# --------------------------------------------------------------------------------------

VARIANTS = [dict(), dict(lambertian=True), dict(specular=False), dict(lambertian=True, specular=False)]


@pytest.mark.parametrize("chunk", range(N_CONFIGS // CHUNK))
def test_stability_sweep_full_bsdf(chunk):
    cfg = _configs(seed=1000 + chunk, k=CHUNK)
    # the prescribed edge values really occur in this chunk
    ex = cfg["exact"]
    for c in (0.0, 1e-8, 1.0, -1.0):
        assert ((cfg["cos_l"] == c) & ex).sum() > 100 and ((cfg["cos_v"] == c) & ex).sum() > 100
    for name in ("roughness", "metallic"):
        for val in (0.0, 1.0):
            assert (cfg[name] == val).sum() > 100

    # back-facing: prescribed cosine <= 0 in the exact (n = +z) rows, or clearly negative
    # in float64 for the rotated rows (|error| of the float32 cast is ~1e-7).
    def cos64(a, b):
        return (cfg[a].double() * cfg[b].double()).sum(-1)
    nl64, nv64 = cos64("n", "l"), cos64("n", "v")
    back = (ex & ((cfg["cos_l"] <= 0) | (cfg["cos_v"] <= 0))) | (nl64 < -1e-6) | (nv64 < -1e-6)
    assert back.sum() > 1000
    # h.v -> 0 with both front-facing really occurs (l ~ -v, both grazing);
    # h.v = |l + v| / 2 for unit l, v (float64 here)
    hv = 0.5 * (cfg["l"].double() + cfg["v"].double()).norm(dim=-1)
    assert ((hv < 1e-6) & ex & (cfg["cos_l"] > 0) & (cfg["cos_v"] > 0)).sum() > 100

    for kw in VARIANTS:
        x = _leaves(cfg)
        f = bsdf.bsdf_eval(x["n"], x["l"], x["v"], x["albedo"], x["roughness"], x["metallic"], **kw)
        _assert_finite_with_grads(f"bsdf_eval{kw}", f, x)
        assert (f >= 0).all(), kw
        assert (f[back] == 0).all(), kw
        # reciprocity. Every quantity is symmetric in (l, v) up to rounding; this sweep
        # (float32, l ~ -v at grazing) is what exposed the old dot(h, v), which differed
        # from dot(h, l) by (|v|^2 - |l|^2)/|l + v| ~ 1e-7/1e-6 and broke this by 750x.
        with torch.no_grad():
            f_sw = bsdf.bsdf_eval(cfg["n"], cfg["v"], cfg["l"], cfg["albedo"], cfg["roughness"],
                                  cfg["metallic"], **kw)
        torch.testing.assert_close(f.detach(), f_sw, rtol=1e-5, atol=0.0)

        # shade(): finite, non-negative, zero for back-facing
        x = _leaves(cfg)
        intensity = torch.full((CHUNK, 1), 100.0, requires_grad=True)
        L = bsdf.shade(x["n"], x["l"], x["v"], x["albedo"], x["roughness"], x["metallic"],
                       intensity, **kw)
        x["intensity"] = intensity
        _assert_finite_with_grads(f"shade{kw}", L, x)
        assert (L >= 0).all() and (L[back] == 0).all()

        # shading while a dropped lobe fades out: the same guarantees at every fade weight,
        # and at w = 1 exactly the full BSDF's image
        if "specular" not in kw:
            lam = kw.get("lambertian", False)
            for w in (0.0, 0.5, 1.0):
                x = _leaves(cfg)
                x["intensity"] = torch.full((CHUNK, 1), 100.0, requires_grad=True)
                Lf = bsdf.shade_fading_lobe(x["n"], x["l"], x["v"], x["albedo"], x["roughness"], x["metallic"],
                                            x["intensity"], w, lambertian=lam)
                _assert_finite_with_grads(f"shade_fading_lobe(w={w}){kw}", Lf, x)
                assert (Lf >= 0).all() and (Lf[back] == 0).all()
                if w == 1.0:
                    torch.testing.assert_close(Lf.detach(), L.detach(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("chunk", range(N_CONFIGS // CHUNK))
def test_stability_sweep_terms(chunk):
    """Each pure term on its documented domain: self-clamping terms get the raw cosines in
    [-1, 1]; the terms documented as 'front-facing cosines assumed' get them clamped to
    [0, 1] exactly as bsdf_eval passes them."""
    cfg = _configs(seed=2000 + chunk, k=CHUNK)
    x = _leaves(cfg)
    n, l, v = x["n"], x["l"], x["v"]
    c, r, m = x["albedo"], x["roughness"], x["metallic"]
    h = bsdf.half_vector(l, v)
    nl, nv, nh, hv = bsdf.dot(n, l), bsdf.dot(n, v), bsdf.dot(n, h), bsdf.dot(h, v)
    nl_c, nv_c, nh_c, hv_c = (t.clamp(0.0, 1.0) for t in (nl, nv, nh, hv))
    alpha = bsdf.ggx_alpha(r)
    f_l, f_v = bsdf.schlick_weight(nl), bsdf.schlick_weight(nv)

    terms = {
        "half_vector": (h, None),
        "ggx_alpha": (alpha, (1e-3, 1.0)),
        "schlick_weight": (f_l, (0.0, 1.0)),
        "fresnel_f0": (bsdf.fresnel_f0(c, m), (0.0, 1.0)),
        "fresnel_schlick": (bsdf.fresnel_schlick(bsdf.fresnel_f0(c, m), hv), (0.0, 1.0)),
        "geometry_g1": (bsdf.geometry_g1(nl, alpha), (0.0, 0.5)),
        "geometry_smith": (bsdf.geometry_smith(nl, nv, alpha), (0.0, 0.25)),
        # documented bound 1 / (16 alpha^2) <= 1 / (16e-6) = 62500 (+ float32 slack)
        "specular_visibility": (bsdf.specular_visibility(nl, nv, alpha), (0.0, 62500.0 * 1.0001)),
        # D <= 1 / (pi alpha^2) <= 1 / (pi 1e-6) in exact arithmetic. In float32 at the alpha
        # floor the denominator nh^2 (a^2 - 1) + 1 ~ a^2 = 1e-6 is a difference of O(1)
        # numbers, so it carries an absolute error of ~ulp(1)/2 = 6e-8, i.e. up to 6%
        # relative, 12% in D ~ 1/denom^2 (measured: 0.5%). It stays >= ~9.4e-7 > 0 (a^2 - 1
        # rounds to > -1), so D stays finite. Hence the documented 15% float32 slack here.
        "ggx_distribution": (bsdf.ggx_distribution(nh, alpha), (0.0, 1.15 / (PI * 1e-6))),
        # f_retro <= 6 c / pi (R = 2, f_l = f_v = 1), worked in test_bsdf_values
        "retro_reflection": (bsdf.retro_reflection(c, r, f_l, f_v, hv_c), (0.0, 6.0001 / PI)),
        # f_d <= 6.25 c / pi (base 1/4 + retro 6 at both-grazing, l = v, r = 1)
        "disney_diffuse": (bsdf.disney_diffuse(c, r, nl_c, nv_c, hv_c), (0.0, 6.2501 / PI)),
        "lambert_diffuse": (bsdf.lambert_diffuse(c), (0.0, 1.0001 / PI)),
        # F D V <= 1 * 1/(pi 1e-6) * 1/(16e-6) (same 15% float32 slack as D)
        "ggx_specular": (bsdf.ggx_specular(c, r, m, nl_c, nv_c, nh_c, hv_c),
                         (0.0, 1.15 / (PI * 1e-6 * 16e-6))),
    }
    # One backward of the sum of all terms: a non-finite gradient in any term makes the
    # total non-finite (finite + inf/nan is never finite), so this is a sufficient check;
    # only on failure re-run per term to name the culprit.
    total = sum(val.sum() for val, _ in terms.values())
    grads = torch.autograd.grad(total, list(x.values()), retain_graph=True)
    if not all(torch.isfinite(gr).all() for gr in grads):
        for name, (val, _) in terms.items():
            _assert_finite_with_grads(name, val, x)
    for name, (val, bounds) in terms.items():
        assert torch.isfinite(val).all(), name
        if bounds is not None:
            # lower bounds exact; upper bounds with 1e-5 relative slack, because float32
            # cosines of unit vectors can exceed 1 by ~1e-7 (e.g. G1 = 0.50000006 at n.x > 1)
            lo, hi = bounds
            val = val.detach()
            assert val.min() >= lo and val.max() <= hi * (1 + 1e-5), \
                (name, float(val.min()), float(val.max()))
    # |h| is 1, or < 1 only where |l + v| < 1e-8 (the documented l = -v fallback)
    hn = h.detach().norm(dim=-1)
    s = (cfg["l"] + cfg["v"]).norm(dim=-1)
    assert torch.all(((hn - 1).abs() < 1e-5) | (s < 1e-8)) and torch.all(hn <= 1 + 1e-5)


def test_exact_edge_grid():
    """Deterministic full product of the edge values with n = +z (cosines exact)."""
    cos_vals = [0.0, 1e-8, 1e-4, 0.5, 1.0, -1e-8, -1.0]
    dphis = [0.0, PI, PI + 1e-6, 0.5 * PI]
    rough_vals = [0.0, 1e-4, math.sqrt(1e-3), 0.5, 1.0]
    metal_vals = [0.0, 0.5, 1.0]
    albedo_vals = [0.0, 0.5, 1.0]
    rows = [(a, b, d, r, m, c) for a in cos_vals for b in cos_vals for d in dphis
            for r in rough_vals for m in metal_vals for c in albedo_vals]
    cl, cv, dp, rr, mm, cc = (torch.tensor(col, dtype=torch.float64) for col in zip(*rows))

    def direction(c, phi):
        s = torch.sqrt((1.0 - c * c).clamp_min(0.0))
        return torch.stack([s * torch.cos(phi), s * torch.sin(phi), c], dim=-1)

    k = len(rows)
    v = direction(cv, torch.full((k,), 0.3, dtype=torch.float64))
    l = direction(cl, 0.3 + dp)
    n = torch.zeros(k, 3, dtype=torch.float64)
    n[:, 2] = 1.0
    back = (cl <= 0) | (cv <= 0)
    for dtype in (torch.float32, torch.float64):
        cfg = dict(n=n.to(dtype), l=l.to(dtype), v=v.to(dtype), albedo=cc[:, None].expand(k, 3).to(dtype),
                   roughness=rr[:, None].to(dtype), metallic=mm[:, None].to(dtype))
        for kw in VARIANTS:
            x = _leaves(cfg)
            f = bsdf.bsdf_eval(x["n"], x["l"], x["v"], x["albedo"], x["roughness"], x["metallic"], **kw)
            _assert_finite_with_grads(f"edge grid {dtype} {kw}", f, x)
            assert (f >= 0).all() and (f[back] == 0).all()
            f_sw = bsdf.bsdf_eval(cfg["n"], cfg["v"], cfg["l"], cfg["albedo"], cfg["roughness"],
                                  cfg["metallic"], **kw)
            torch.testing.assert_close(f.detach(), f_sw, rtol=1e-5, atol=0.0)
            # albedo = 0 and metallic = 0 leaves only the 0.04 dielectric specular
            # (exactly zero without the specular lobe)
            if not kw.get("specular", True):
                dark = (cc == 0)
                assert (f[dark] == 0).all()


# --------------------------------------------------------------------------------------
# 5. White furnace
# --------------------------------------------------------------------------------------
#
# Directional albedo A(v) = int f(l, v) (n.l) dw_l, estimated by Monte Carlo in float64
# with a fixed seed. The tolerance is 5 standard errors of the mean, with the standard
# error estimated from the samples themselves (sd / sqrt(N)): for a fixed seed the test
# is deterministic, and if the true A were exactly on the bound a 5-sigma excursion of
# the estimator would have probability ~3e-7, so a failure means the bound is violated,
# not bad luck. N = 2^17 per case keeps the whole file well under the time budget.
#
# Specular lobe, F0 = 1 (metallic = 1, albedo = 1: F == 1 exactly, the worst case; the
# diffuse lobe is weighted by 1 - m = 0 so bsdf_eval is exactly f_s):
#   sampler: h ~ D(h) (n.h) (standard GGX sampling, tan^2 th_h = alpha^2 u / (1 - u)),
#            l = reflect(v, h), pdf_l = D(h) (n.h) / (4 h.v), samples with n.l <= 0 count 0;
#   weight:  f_s(l, v) (n.l) / pdf_l.
# At r = 1 the result is exact: alpha = 1, D = 1/pi, G/(4 nl nv) = 1/16, F = 1
#   -> A = int 1/(16 pi) (n.l) dw = 1/16 = 0.0625 for every view (and with cosine
#   sampling the weight pi f_s = 1/16 is constant: zero variance).
# The paper's G1(x) = n.x / (2 [alpha + (1-alpha) n.x]) is 1/2 at n.x = 1 (the usual
# Schlick-Smith G1 is 1 there), so G <= 1/4 and this lobe reflects at most ~1/4 of the
# energy: the "<= 1" furnace bound holds with a large margin. The tighter A <= 1/4 is
# proved at n.v = 1 (A_v = 1, n.l / A_l <= 1, int D (h.v) dw_h = int D (n.h) dw_h = 1, so
# A <= 4 / 16) and is asserted for the other views as a measured property.
# Measured (2^17 samples, GGX sampling; SE <= 6e-4):
#   n.v:      1.0     0.5     0.2     0.05
#   r = 0.05: 0.2500  0.2487  0.2451  0.2278
#   r = 0.2 : 0.2494  0.2301  0.1853  0.1118
#   r = 0.5 : 0.2166  0.1528  0.1113  0.0969   (cosine sampling: 0.2176 0.1536 0.1107 0.0970)
#   r = 1.0 : 0.0622  0.0623  0.0630  0.0625   (exact 1/16; cosine sampling 0.0625 exactly)

N_MC = 1 << 17
SPEC_ROUGH = [0.05, 0.2, 0.5, 1.0]
VIEW_COS = [1.0, 0.5, 0.2, 0.05]


def _view(cos_v):
    s = math.sqrt(max(0.0, 1.0 - cos_v * cos_v))
    return torch.tensor([[s, 0.0, cos_v]], dtype=torch.float64)


def _mean_se(w):
    return float(w.mean()), float(w.std() / math.sqrt(w.numel()))


def _ggx_d(nh, alpha):
    # independent copy of the standard GGX NDF (the sampler's own density)
    a2 = alpha * alpha
    return a2 / (PI * (nh * nh * (a2 - 1.0) + 1.0) ** 2)


def _albedo_ggx_sampling(r, cos_v, seed, **material):
    g = torch.Generator().manual_seed(seed)
    alpha = max(r * r, 1e-3)
    u1 = torch.rand(N_MC, generator=g, dtype=torch.float64)
    u2 = torch.rand(N_MC, generator=g, dtype=torch.float64)
    tan2 = alpha * alpha * u1 / (1.0 - u1)
    cos_h = 1.0 / torch.sqrt(1.0 + tan2)
    sin_h = torch.sqrt((1.0 - cos_h * cos_h).clamp_min(0.0))
    phi = 2 * PI * u2
    h = torch.stack([sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h], -1)
    v = _view(cos_v).expand(N_MC, 3)
    hv = (h * v).sum(-1, keepdim=True)
    l = 2.0 * hv * h - v
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(N_MC, 3)
    nl = l[:, 2:3]
    pdf = _ggx_d(cos_h[:, None], alpha) * cos_h[:, None] / (4.0 * hv.abs())
    f = _eval_furnace(n, l, v, r, **material)
    w = torch.where((nl > 0) & (hv > 0), f * nl / pdf, torch.zeros_like(f))
    return _mean_se(w[:, 0])


def _albedo_cosine_sampling(r, cos_v, seed, **material):
    g = torch.Generator().manual_seed(seed)
    u1 = torch.rand(N_MC, generator=g, dtype=torch.float64)
    u2 = torch.rand(N_MC, generator=g, dtype=torch.float64)
    # Malley: pdf = n.l / pi  ->  weight = f (n.l) / pdf = pi f
    sin_t, phi = torch.sqrt(u1), 2 * PI * u2
    l = torch.stack([sin_t * torch.cos(phi), sin_t * torch.sin(phi), torch.sqrt(1.0 - u1)], -1)
    v = _view(cos_v).expand(N_MC, 3)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(N_MC, 3)
    f = _eval_furnace(n, l, v, r, **material)
    return _mean_se(PI * f[:, 0])


def _eval_furnace(n, l, v, r, metallic, specular):
    k = n.shape[0]
    albedo = torch.ones(k, 3, dtype=torch.float64)
    return bsdf.bsdf_eval(n, l, v, albedo, torch.full((k, 1), r, dtype=torch.float64),
                          torch.full((k, 1), metallic, dtype=torch.float64), specular=specular)


SPEC = dict(metallic=1.0, specular=True)     # f == f_s with F == 1
DIFF = dict(metallic=0.0, specular=False)    # f == f_d with c = 1


@pytest.mark.parametrize("r", SPEC_ROUGH)
def test_white_furnace_specular(r):
    for i, cos_v in enumerate(VIEW_COS):
        mean, se = _albedo_ggx_sampling(r, cos_v, seed=100 + i, **SPEC)
        assert mean <= 1.0 + 5 * se, (r, cos_v, mean, se)
        # the paper's G caps the lobe at ~1/4 (see the comment above): A <= 1/4 + 5 se
        assert mean <= 0.25 + 5 * se, (r, cos_v, mean, se)
        assert mean > 0.05
        if r == 1.0:
            assert abs(mean - 1.0 / 16.0) <= 5 * se + 1e-12, (cos_v, mean, se)
        if r >= 0.5:
            # an independent estimator (cosine sampling) must agree within 5 combined SE
            mean2, se2 = _albedo_cosine_sampling(r, cos_v, seed=200 + i, **SPEC)
            assert abs(mean - mean2) <= 5 * math.hypot(se, se2) + 1e-12, (r, cos_v, mean, mean2)
            if r == 1.0:
                assert abs(mean2 - 1.0 / 16.0) < 1e-12 and se2 < 1e-12


# Diffuse lobe (c = 1, m = 0, specular off), cosine sampling (weight pi f_d).
# What the math says, worked by hand (B(a, b) Beta integrals, mu = n.l,
# int_0^1 mu (1-mu)^5 dmu = 1/42, int_0^1 mu^2 (1-mu)^5 dmu = 1/168,
# int_0^1 mu^3 (1-mu)^5 dmu = 1/504):
#   * n.v = 1 (f_v = 0, l.v = mu, (h.v)^2 = (1 + mu)/2, R = r (1 + mu)):
#       A = 2 int mu [(1 - f_l/2) + r (1 + mu) f_l] dmu = 41/42 + 2 r (1/42 + 1/168)
#         = 41/42 + 5 r / 84                       (0.9762 at r=0, 1.0357 at r=1)
#   * n.v -> 0 (f_v = 1, v = x, (h.v)^2 = (1 + s)/2 with s = sin th cos phi, whose
#     azimuthal means are <s> = 0, <s^2> = sin^2 th / 2; the bracket is 1 + f_l R):
#       pi f_d = (1 - f_l/2)/2 + R + f_l R^2
#       A = 41/84 + r + 2 r^2 int mu (1-mu)^5 (3/2 - mu^2/2) dmu = 41/84 + r + 5 r^2 / 72
#                                                   (0.4881 at r=0, 1.5575 at r=1)
# So the Disney diffuse (paper and Burley 2012 alike) is NOT energy conserving for rough
# surfaces: A = 1 exactly at r = 0.4, n.v = 1, and A -> 1.5575 at r = 1, grazing view.
# An independent numpy quadrature scan (n.v on a 0.025 grid) puts max over n.v of A at
# n.v = 1 for r <= 0.4 (so A <= 41/42 + 5r/84 <= 1 there) and at n.v -> 0 for r = 1
# (global maximum 41/84 + 1 + 5/72 = 1.5575 over r in [0, 1], since f_d is non-decreasing
# in r: d/dR [R (a + b (R - 1))] = a - b + 2 b R >= 0 with a = f_l + f_v >= b = f_l f_v,
# and R = 2 r (h.v)^2 grows with r); r = 0.5 peaks at ~1.025
# near n.v = 0.15. The asserted bounds are those: A <= 1 for r <= 0.4, A <= 1.5575 for
# all r <= 1, plus agreement with both closed forms. Measured (2^17 samples, SE <= 2e-3):
#   n.v:      1.0     0.5     0.2     0.05    1e-9    | closed n.v=1  closed n.v->0
#   r = 0   : 0.9760  0.9610  0.8163  0.5985  0.4880  | 0.9762        0.4881
#   r = 0.25: 0.9910  0.9846  0.9189  0.8044  0.7421  | 0.9911        0.7424
#   r = 0.4 : 1.0000  0.9989  0.9819  0.9311  0.8988  | 1.0000        0.8992
#   r = 0.5 : 1.0060  1.0085  1.0246  1.0170  1.0050  | 1.0060        1.0055
#   r = 1.0 : 1.0360  1.0573  1.2449  1.4624  1.5572  | 1.0357        1.5575

DIFF_ROUGH = [0.0, 0.25, 0.4, 0.5, 1.0]


@pytest.mark.parametrize("r", DIFF_ROUGH)
def test_white_furnace_diffuse(r):
    closed_normal = 41.0 / 42.0 + 5.0 * r / 84.0
    closed_grazing = 41.0 / 84.0 + r + 5.0 * r * r / 72.0
    sup_all = 41.0 / 84.0 + 1.0 + 5.0 / 72.0
    for i, cos_v in enumerate([1.0, 0.5, 0.2, 0.05, 1e-9]):
        mean, se = _albedo_cosine_sampling(r, cos_v, seed=300 + i, **DIFF)
        assert mean <= sup_all + 5 * se, (r, cos_v, mean, se)
        if r <= 0.4:
            assert mean <= 1.0 + 5 * se, (r, cos_v, mean, se)
        if cos_v == 1.0:
            assert abs(mean - closed_normal) <= 5 * se + 1e-9, (r, mean, closed_normal, se)
        if cos_v == 1e-9:
            # n.v = 1e-9 instead of 0 (0 is masked to zero) changes A by O(1e-8)
            assert abs(mean - closed_grazing) <= 5 * se + 1e-6, (r, mean, closed_grazing, se)
    if r == 1.0:
        # documented non-conservation: the rough grazing albedo really exceeds 1
        assert closed_grazing > 1.5


def test_white_furnace_lambert():
    # Lambert c = 1: A = int (1/pi) (n.l) dw = 1 exactly; pi f = 1, zero variance
    g = torch.Generator().manual_seed(400)
    u = torch.rand(1000, 2, generator=g, dtype=torch.float64)
    l = torch.stack([torch.sqrt(u[:, 0]) * torch.cos(2 * PI * u[:, 1]),
                     torch.sqrt(u[:, 0]) * torch.sin(2 * PI * u[:, 1]), torch.sqrt(1 - u[:, 0])], -1)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(1000, 3)
    v = _view(0.3).expand(1000, 3)
    f = bsdf.bsdf_eval(n, l, v, torch.ones(1000, 3, dtype=torch.float64),
                       torch.full((1000, 1), 0.5, dtype=torch.float64),
                       torch.zeros(1000, 1, dtype=torch.float64), lambertian=True, specular=False)
    torch.testing.assert_close(PI * f, torch.ones_like(f), rtol=1e-12, atol=0.0)
