"""bench/evidence_lights.py: the two-light fit of the material evidence against a reference NNLS
and against colours a key and a fill light make, the irradiance by hand, and its input errors."""

import json
import math

import numpy as np
import pytest
import torch
from scipy.optimize import nnls

from bench.evidence_lights import (_nnls_two, best_fill_residuals, fill_candidates, fit_two_lights, light_geometry,
                                   scene_lights)
from nepf_core import bsdf
from nepf_core.render import material_evidence as me

GOLD = (1.0, 0.78, 0.34)
RED = (0.6, 0.2, 0.1)


def _unit(t):
    return torch.nn.functional.normalize(t, dim=-1)


def test_the_two_variable_nnls_matches_scipy():
    rng = np.random.default_rng(0)
    for _ in range(200):
        M = rng.normal(size=(12, 2)) * rng.uniform(0.1, 3.0, size=2)
        y = rng.normal(size=12)
        ref, _ = nnls(M, y)
        G, t = M.T @ M, M.T @ y
        b1, b2 = _nnls_two(*(torch.tensor(v, dtype=torch.float64) for v in (G[0, 0], G[1, 1], G[0, 1], t[0], t[1])))
        assert [float(b1), float(b2)] == pytest.approx(ref.tolist(), abs=1e-9)


def _scene(count: int, seed: int):
    """Points on a lit cap, 8 cameras each, a key light above and a fill from the side."""
    g = torch.Generator().manual_seed(seed)
    n = _unit(torch.randn(count, 3, generator=g) + torch.tensor([0.0, 0.0, 1.5]))
    v = _unit(torch.randn(count, 8, 3, generator=g))
    v = torch.where((v * n[:, None]).sum(-1, keepdim=True) < 0, -v, v)
    valid = (v * n[:, None]).sum(-1) > me.MIN_FACING_COS
    key = _unit(torch.tensor([0.2, 0.1, 1.0])).expand_as(n)
    fill = _unit(torch.tensor([-1.0, 0.3, 0.4])).expand_as(n)
    return n, v, valid, key, fill


def _two_light_colours(n, v, key, fill, albedo, r, m, fill_intensity):
    P, K = v.shape[:2]
    rep = lambda t: t[:, None].expand(P, K, 3)
    a = torch.tensor(albedo).expand(P, K, 3)
    full = lambda val: torch.full((P, K, 1), float(val))
    shade = lambda l, I: bsdf.shade(rep(n), rep(l), v, a, full(r), full(m), full(I), kind="gltf")
    return shade(key, 3.0) + shade(fill, fill_intensity)


def test_one_light_makes_the_two_light_fit_the_one_light_fit():
    """The model nests the one-light one (beta_2 = 0): on one light's colours its residual is the
    one-light residual or lower, at every hypothesis."""
    n, v, valid, key, fill = _scene(64, 1)
    A1, B1 = me.hypothesis_basis(n, key, v)
    A2, B2 = me.hypothesis_basis(n, fill, v)
    for albedo, m in ((GOLD, 1.0), (RED, 0.0)):
        c = _two_light_colours(n, v, key, fill, albedo, 0.3, m, 0.0)
        one = me.fit_hypotheses(c, A1, B1, valid)
        two = fit_two_lights(c, A1, B1, A2, B2, valid)
        assert bool((two <= one * (1 + 1e-4) + 1e-6).all())
        G = len(me.ROUGHNESS_GRID)
        h = (G if m else 0) + me.ROUGHNESS_GRID.index(0.3)
        assert torch.allclose(two[:, h], torch.full((64,), me.RESIDUAL_FLOOR), rtol=1e-3)


def test_a_fill_lit_metal_is_a_metal_to_the_two_light_fit_and_not_to_the_key_alone():
    """Gold metal at roughness 0.3 lit by a key and a fill of 60 % of its intensity: the generating
    hypothesis fits to the floor with both lights, the key alone misses metals that the two-light
    evidence calls, and a red dielectric under the same lights stays a dielectric."""
    n, v, valid, key, fill = _scene(256, 2)
    A1, B1 = me.hypothesis_basis(n, key, v)
    A2, B2 = me.hypothesis_basis(n, fill, v)
    G = len(me.ROUGHNESS_GRID)
    metal = _two_light_colours(n, v, key, fill, GOLD, 0.3, 1.0, 1.8)
    e_two = fit_two_lights(metal, A1, B1, A2, B2, valid)
    assert torch.allclose(e_two[:, G + me.ROUGHNESS_GRID.index(0.3)], torch.full((256,), me.RESIDUAL_FLOOR), rtol=1e-3)
    two = me.evidence_from_residuals(e_two)
    one = me.evidence_from_residuals(me.fit_hypotheses(metal, A1, B1, valid))
    sure = two.metallic_confidence > 0.1
    assert float(sure.float().mean()) > 0.6
    assert float((two.metallic[sure] > 0.5).float().mean()) > 0.97
    assert float((one.metallic > 0.5).float().mean()) < float((two.metallic > 0.5).float().mean()) - 0.1
    dielectric = _two_light_colours(n, v, key, fill, RED, 0.3, 0.0, 1.8)
    ev = me.evidence_from_residuals(fit_two_lights(dielectric, A1, B1, A2, B2, valid))
    assert float((ev.metallic > 0.5).float().mean()) < 0.03


def test_fill_candidates_cover_the_sphere_evenly():
    """Unit vectors whose mean is ~0, and every direction on a fine grid within the lattice's
    spacing (about sqrt(4 pi / M) rad) of its nearest candidate."""
    c = fill_candidates(32).double()
    assert torch.allclose(c.norm(dim=-1), torch.ones(32, dtype=torch.float64), atol=1e-6)
    assert float(c.mean(0).norm()) < 0.02
    probe = _unit(torch.randn(4000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64))
    worst = math.degrees(math.acos(float((probe @ c.T).max(1).values.min())))
    assert worst < math.degrees(math.sqrt(4 * math.pi / 32))


def test_a_searched_fill_finds_a_fill_lit_metal_and_keeps_a_dielectric():
    """The fill put on a candidate direction: the searched fit is the true two-light fit there
    (residual at the floor on the generating hypothesis), it calls the fill-lit gold metal where
    the key alone does not, it is never above the one-light fit, and the red dielectric stays one."""
    n, v, valid, key, _ = _scene(256, 3)
    cands = fill_candidates(32)
    fill = cands[int(((cands @ torch.tensor([-0.7, 0.2, 0.5])).argmax()))].expand_as(n)
    G = len(me.ROUGHNESS_GRID)
    metal = _two_light_colours(n, v, key, fill, GOLD, 0.3, 1.0, 1.8)
    e = best_fill_residuals(metal, n, key, v, valid, cands)
    lit_by_fill = (n * fill).sum(-1) > 0.3
    h = G + me.ROUGHNESS_GRID.index(0.3)
    assert float(e[lit_by_fill, h].max()) < me.RESIDUAL_FLOOR * 1.01
    A1, B1 = me.hypothesis_basis(n, key, v)
    e_one = me.fit_hypotheses(metal, A1, B1, valid)
    assert bool((e <= e_one * (1 + 1e-4) + 1e-6).all())
    called = lambda res: float((me.evidence_from_residuals(res).metallic[lit_by_fill] > 0.5).float().mean())
    assert called(e) > 0.9 and called(e) > called(e_one) + 0.1
    dielectric = _two_light_colours(n, v, key, fill, RED, 0.3, 0.0, 1.8)
    ev = me.evidence_from_residuals(best_fill_residuals(dielectric, n, key, v, valid, cands))
    assert float((ev.metallic > 0.5).float().mean()) < 0.03


def test_light_geometry_by_hand():
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    lights = [{"position_world": [0.0, 0.0, 2.0], "intensity_rgb": [4.0, 4.0, 4.0]},
              {"position_world": [3.0, 0.0, 0.0], "intensity_rgb": [1.0, 2.0, 3.0]}]
    u, e = light_geometry(x, nrm, lights)
    assert u[0, 0].tolist() == pytest.approx([0.0, 0.0, 1.0])
    assert e[0, 0] == pytest.approx(4.0 / 4.0)                                  # I cos / d^2 = 4 * 1 / 4
    d = math.sqrt(1.0 + 4.0)                                                    # (1, 0, 0) -> (0, 0, 2)
    assert e[0, 1] == pytest.approx(4.0 * (2.0 / d) / d ** 2)
    assert e[1].tolist() == pytest.approx([0.0, 0.0])                           # in the tangent plane: cos 0


def test_scene_lights_errors(tmp_path):
    (tmp_path / "s" / "gt").mkdir(parents=True)
    with pytest.raises(SystemExit, match="lights.json"):
        scene_lights(tmp_path / "s")
    three = [{"type": "point", "position_world": [0, 0, 1], "intensity_rgb": [1, 1, 1]}] * 3
    (tmp_path / "s" / "gt" / "lights.json").write_text(json.dumps({"lights": three}))
    with pytest.raises(SystemExit, match="3 point lights"):
        scene_lights(tmp_path / "s")
    assert str(tmp_path) not in str(pytest.raises(SystemExit, scene_lights, tmp_path / "s").value)
