"""The material evidence (nepf_core/render/material_evidence.py): its basis against the glTF BSDF,
exact fits, a half-metal / half-dielectric sphere it must split, a learned light some degrees off,
the loss term's value and its place in a fit."""

import dataclasses
import math

import pytest
import torch

from nepf_core import bsdf
from nepf_core.config import fast, paper, tiny
from nepf_core.losses import LossConfig, compute_losses
from nepf_core.model import NePFModel
from nepf_core.rays import RayBatch
from nepf_core.render import material_evidence as me
from nepf_core.render.renderer import render_rays

GOLD = (1.0, 0.78, 0.34)
RED = (0.6, 0.2, 0.1)


def _unit(t):
    return torch.nn.functional.normalize(t, dim=-1)


def _hemisphere_dirs(n: torch.Tensor, k: int, g: torch.Generator) -> torch.Tensor:
    v = _unit(torch.randn(n.shape[0], k, 3, generator=g))
    return torch.where((v * n[:, None]).sum(-1, keepdim=True) < 0, -v, v)


def _tilt(l: torch.Tensor, deg: float, g: torch.Generator) -> torch.Tensor:
    t = _unit(torch.cross(l, torch.randn(l.shape, generator=g), dim=-1))
    return _unit(l * math.cos(math.radians(deg)) + t * math.sin(math.radians(deg)))


def _colours(n, l, v, albedo, r, m):
    """What a perfectly fitted radiance field shows: the glTF BSDF under a light of intensity 3."""
    P, K = v.shape[:2]
    rep = lambda t: t[:, None].expand(P, K, 3)
    a = torch.as_tensor(albedo, dtype=torch.float32).expand(P, K, 3) if not torch.is_tensor(albedo) else rep(albedo)
    full = lambda val: torch.as_tensor(val, dtype=torch.float32).reshape(-1, 1, 1).expand(P, K, 1)
    return bsdf.shade(rep(n), rep(l), v, a, full(r), full(m), torch.full((P, K, 1), 3.0), kind="gltf").clamp(0, 1)


def test_the_basis_is_the_gltf_bsdf_affine_in_the_albedo():
    g = torch.Generator().manual_seed(0)
    n = _unit(torch.randn(5, 3, generator=g))
    l = _hemisphere_dirs(n, 1, g)[:, 0]
    v = _hemisphere_dirs(n, 4, g)
    A, B = me.hypothesis_basis(n, l, v)
    G = len(me.ROUGHNESS_GRID)
    assert A.shape == B.shape == (5, 2 * G, 4)
    albedo = torch.tensor([0.3, 0.55, 0.9])
    for h in range(2 * G):
        m, r = float(h >= G), me.ROUGHNESS_GRID[h % G]
        ref = bsdf.bsdf_eval(n[:, None].expand(5, 4, 3), l[:, None].expand(5, 4, 3), v, albedo.expand(5, 4, 3),
                             torch.full((5, 4, 1), r), torch.full((5, 4, 1), m), kind="gltf")
        got = A[:, h, :, None] * albedo + B[:, h, :, None]       # beta = E (n.l) = 1: the BSDF itself
        assert torch.allclose(got, ref, rtol=1e-4, atol=1e-6), (m, r)


def test_the_generating_hypothesis_fits_to_the_floor():
    g = torch.Generator().manual_seed(1)
    n = _unit(torch.randn(32, 3, generator=g))
    l = _hemisphere_dirs(n, 1, g)[:, 0]
    v = _hemisphere_dirs(n, 8, g)
    valid = (v * n[:, None]).sum(-1) > 0.1
    G = len(me.ROUGHNESS_GRID)
    A, B = me.hypothesis_basis(n, l, v)
    for h, (m, albedo) in {2: (0.0, RED), G + 3: (1.0, GOLD)}.items():
        r = me.ROUGHNESS_GRID[h % G]
        beta = 0.7
        c = beta * (A[:, h, :, None] * torch.tensor(albedo) + B[:, h, :, None])     # unclipped, exact
        e = me.fit_hypotheses(c, A, B, valid)
        assert torch.allclose(e[:, h], torch.full((32,), me.RESIDUAL_FLOOR), rtol=1e-3), (m, r)
        other_kind = e[:, G:] if h < G else e[:, :G]       # the other kind cannot fit it as well
        assert float((other_kind.min(1).values > me.RESIDUAL_FLOOR * 1.05).float().mean()) > 0.9


def _sphere_points(count: int, g: torch.Generator):
    n = _unit(torch.randn(count, 3, generator=g) + torch.tensor([0.0, 0.0, 1.2]))   # the lit cap
    return n


@pytest.mark.parametrize("tilt_deg", [0.0, 15.0])
def test_a_half_metal_half_dielectric_sphere_splits(tilt_deg):
    """x < 0 gold metal, x >= 0 red dielectric, both roughness 0.3, one point light above; 8 views
    per point. The evidence must say metal on one half and dielectric on the other, and recover
    the roughness to within one grid step, also when the learned light is 15 deg off."""
    g = torch.Generator().manual_seed(2)
    n = _sphere_points(256, g)
    light = _unit(torch.tensor([0.2, 0.1, 1.0]))
    l = light.expand_as(n)
    v = _hemisphere_dirs(n, 8, g)
    valid = (v * n[:, None]).sum(-1) > me.MIN_FACING_COS
    metal = n[:, 0] < 0
    albedo = torch.where(metal[:, None], torch.tensor(GOLD), torch.tensor(RED))
    c = _colours(n, l, v, albedo, 0.3, metal.float())
    l_learned = _tilt(l, tilt_deg, g) if tilt_deg else l
    ev = me.material_evidence(c, n, l_learned, v, valid)
    called, sure = ev.metallic > 0.5, ev.metallic_confidence > 0.1
    # a metal seen only away from its lobe is black from every camera (or clipped white in it):
    # nothing tells it apart, and the evidence says so with ~0 confidence rather than a wrong call
    assert float(sure.float().mean()) > 0.7
    assert float((called == metal)[sure].float().mean()) > 0.97
    assert float((called == metal)[~metal].float().mean()) == 1.0      # no dielectric called metal
    wrong = (called != metal).float()
    assert float((ev.metallic_confidence * wrong).sum() / ev.metallic_confidence.sum()) < 0.02
    # the true roughness at the true light; a neighbour of it on the grid (0.2 or 0.45) when tilted
    median = float(ev.roughness[metal].median())
    assert median == pytest.approx(0.3) if not tilt_deg else median in (pytest.approx(0.2), pytest.approx(0.3),
                                                                         pytest.approx(0.45))


def test_without_the_light_search_a_tilted_light_costs_metals():
    """The reason for :func:`light_candidates`: at the tilted light alone fewer metals are found."""
    g = torch.Generator().manual_seed(3)
    n = _sphere_points(256, g)
    l = _unit(torch.tensor([0.2, 0.1, 1.0])).expand_as(n)
    v = _hemisphere_dirs(n, 8, g)
    valid = (v * n[:, None]).sum(-1) > me.MIN_FACING_COS
    c = _colours(n, l, v, torch.tensor(GOLD).expand_as(n), 0.2, torch.ones(256))
    tilted = _tilt(l, 25.0, g)
    with_search = me.material_evidence(c, n, tilted, v, valid)
    without = me.material_evidence(c, n, tilted, v, valid, search_light=False)
    assert float(with_search.metallic.mean()) > float(without.metallic.mean()) + 0.05
    sure = with_search.metallic_confidence > 0.1
    assert float(with_search.metallic[sure].mean()) > 0.95


def test_light_candidates_are_unit_and_tilted_by_the_stated_angles():
    l = _unit(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.3, -0.5, 0.2]]))
    cand = me.light_candidates(l)
    assert cand.shape == (3, 1 + len(me.LIGHT_TILTS_DEG) * me.LIGHT_AZIMUTHS, 3)
    assert torch.allclose(cand.norm(dim=-1), torch.ones(cand.shape[:2]), atol=1e-5)
    ang = torch.rad2deg(torch.acos((cand * l[:, None]).sum(-1).clamp(-1, 1)))
    expected = [0.0] + [t for t in me.LIGHT_TILTS_DEG for _ in range(me.LIGHT_AZIMUTHS)]
    assert torch.allclose(ang, torch.tensor(expected).expand_as(ang), atol=0.05)


def test_a_flat_view_independent_colour_is_not_called_metal():
    """A Lambertian-looking point (the same colour from every camera) gives a dielectric or no
    confident call: a metal has no view-independent floor."""
    g = torch.Generator().manual_seed(4)
    n = _sphere_points(128, g)
    v = _hemisphere_dirs(n, 8, g)
    valid = (v * n[:, None]).sum(-1) > me.MIN_FACING_COS
    c = torch.tensor([0.3, 0.2, 0.1]).expand(128, 8, 3).clone()
    ev = me.material_evidence(c, n, _unit(n + 0.3), v, valid)
    assert float((ev.metallic_confidence * ev.metallic).mean()) < 0.1


class _SDF:
    """``f(x)`` and ``(f, features)`` as :class:`nepf_core.fields.sdf_grid.GridSDF` gives them."""

    def __init__(self, fn):
        self.sdf = fn

    def __call__(self, x):
        return self.sdf(x), torch.zeros(x.shape[0], 1)


class _SphereModel:
    """A sphere of radius 0.5 whose radiance network *is* a gold metal under one light."""

    light = _unit(torch.tensor([0.3, -0.2, 1.0]))

    def __init__(self, sdf_fn=lambda p: p.norm(dim=-1) - 0.5):
        self.sdf = _SDF(sdf_fn)

    def radiance(self, x, d, n, f, with_logits=False):
        k = x.shape[0]
        return bsdf.shade(n, self.light.expand(k, 3), -d, torch.tensor(GOLD).expand(k, 3), torch.full((k, 1), 0.3),
                          torch.ones(k, 1), torch.full((k, 1), 3.0), kind="gltf").clamp(0, 1)


def test_gather_evidence_uses_only_facing_cameras_that_see_the_point():
    model = _SphereModel()
    x = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5]])
    n = _unit(x)
    cams = torch.tensor([[0.0, 0.0, 3.0], [1.0, 0.0, 3.0], [0.0, 1.0, 3.0], [-1.0, 0.0, 3.0], [0.0, 0.0, -3.0],
                         [3.0, 0.0, 0.0]])
    c, v, valid = me.views_of_points(model, x, n, cams, 6, torch.Generator().manual_seed(0))
    # the top point sees the four cameras above it; the camera at +x is grazing (n.v = 0) for
    # both; the bottom point sees only the camera below
    assert valid.sum(-1).tolist() == [4, 1]
    # each colour is the point seen from that camera: v points toward the camera
    for p in range(2):
        for k in valid[p].nonzero().flatten().tolist():
            to_cam = _unit(cams - x[p])
            assert any(torch.allclose(v[p, k], t, atol=1e-6) for t in to_cam)
            expected = bsdf.shade(n[p:p + 1], model.light[None], v[p, k][None], torch.tensor([GOLD]),
                                  torch.tensor([[0.3]]), torch.ones(1, 1), torch.full((1, 1), 3.0), kind="gltf")
            assert torch.allclose(c[p, k], expected[0].clamp(0, 1), atol=1e-6)
    eb = me.gather_evidence(model, x, n, model.light.expand(2, 3), torch.ones(2, dtype=torch.bool), cams,
                            torch.Generator().manual_seed(0))
    assert eb.rays.tolist() == [0]                    # the bottom point has fewer than MIN_VIEWS views
    # an occluder between the point and the cameras (inside the unit sphere, where the march looks)
    blocked = _SphereModel(lambda p: torch.minimum(p.norm(dim=-1) - 0.5,
                                                   (p - torch.tensor([0.0, 0.0, 0.8])).norm(dim=-1) - 0.1))
    _, _, valid_b = me.views_of_points(blocked, x[:1], n[:1], cams[:1], 1, None)
    assert valid_b.tolist() == [[False]]


def test_no_lit_point_or_too_few_views_give_no_evidence():
    model = _SphereModel()
    x = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5]])
    n = _unit(x)
    cams = torch.tensor([[0.0, 0.0, 3.0], [1.0, 0.0, 3.0], [0.0, 1.0, 3.0]])
    none_lit = me.gather_evidence(model, x, n, n, torch.zeros(2, dtype=torch.bool), cams)
    only_bottom = me.gather_evidence(model, x, n, n, torch.tensor([False, True]), cams)   # no camera below
    for eb in (none_lit, only_bottom):
        assert eb.rays.numel() == 0 and eb.evidence.metallic.shape == (0,)
        assert eb.evidence.residual.shape == (0, 2 * len(me.ROUGHNESS_GRID))


def test_the_term_pulls_toward_the_targets_by_their_confidence():
    torch.manual_seed(0)
    cfg = tiny()
    model = NePFModel(cfg.model)
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([[0.0, 0.0, -2.5]]).repeat(8, 1)
    d = _unit(torch.randn(8, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]))
    rays = RayBatch(origins=o, directions=d, rgb=torch.zeros(8, 3))
    out = render_rays(model, rays, cfg.render, train=True)
    ev = me.MaterialEvidence(metallic=torch.tensor([1.0, 0.0]), metallic_confidence=torch.tensor([0.5, 1.0]),
                             roughness=torch.tensor([0.2, 0.8]),
                             residual=torch.zeros(2, 14))
    out.material_evidence = me.EvidenceBatch(rays=torch.tensor([2, 5]), evidence=ev)
    loss_cfg = dataclasses.replace(LossConfig(), w_material_evidence=1.0)
    got = compute_losses(out, rays, loss_cfg, use_mask=False)["loss_material_evidence"]
    s = out.surface
    expected = (0.5 * (1.0 - s.metallic[2]) + 1.0 * s.metallic[5]) / 2.0     # the roughness is not pulled
    assert float(got.detach()) == pytest.approx(float(expected.detach()), rel=1e-5)
    grads = torch.autograd.grad(got, [p for p in model.parameters()], allow_unused=True)
    reached = {name.split(".")[0] for (name, _), gr in zip(model.named_parameters(), grads)
               if gr is not None and gr.abs().sum() > 0}
    assert "material" in reached and reached <= {"material", "sdf"}     # not the light
    out.material_evidence = me.EvidenceBatch(rays=torch.zeros(0, dtype=torch.long),
                                             evidence=me._no_evidence(torch.zeros(1)))
    assert float(compute_losses(out, rays, loss_cfg, use_mask=False)["loss_material_evidence"]) == 0.0
    out.material_evidence = None     # a render outside the training step: the term is left out
    assert "loss_material_evidence" not in compute_losses(out, rays, loss_cfg, use_mask=False)


def test_presets_and_the_bsdf_it_needs():
    assert paper().loss.w_material_evidence == 0     # not in the paper
    assert LossConfig().w_material_evidence == 0
    cfg = fast()
    assert cfg.loss.w_material_evidence > 0 and cfg.loss.w_metallic_unseen > 0   # beside the prior, not in place
    cfg.check()
    cfg.render.bsdf_kind = "paper"
    with pytest.raises(ValueError, match="bsdf_kind"):
        cfg.check()


def test_a_fast_fit_trains_the_term(tmp_path):
    """In a fit the step gathers evidence at lit foreground points and logs the term."""
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.fields.sdf_grid import GridSDFConfig
    from nepf_core.train import fit
    from nepf_core.train.hooks import TrainHooks

    make_scene(tmp_path / "s", n_views=8, n_test=0, resolution=24, supersample=1, write_mesh=False)
    cfg = fast()
    cfg.model.sdf_grid = GridSDFConfig(base_resolution=8, max_resolution=32)
    cfg.model.occupancy_resolution = 16
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every = 6, 96, 1
    cfg.train.sync_every, cfg.train.eval_every_s = 0, 0.0
    cfg.loss.w_material_evidence = 1e-3

    class Seen(TrainHooks):
        rows = []

        def after_step(self, run, step, out, losses):
            self.rows.append((out.material_evidence.rays.numel(), float(losses["loss_material_evidence"].detach())))
            # the record carries the evidence to every ray: a share per ray, recomputed here from
            # the record's sums at the rays' surface points
            rec = run.metal_record
            i = rec.cells(out.surface.x)
            want = rec.metal[i] / (rec.confidence[i] + rec.prior_confidence)
            assert out.metal_share.shape == (len(out.weight_sum),) and torch.equal(out.metal_share, want)
            self.record = (rec.metal.clone(), rec.confidence.clone())

    scene = load_scene(tmp_path / "s" / "dtu")
    fit(scene, tmp_path / "run", cfg, device="cpu", hooks=[seen := Seen()])
    assert Seen.rows and any(m > 0 and v > 0 for m, v in Seen.rows)
    assert float(seen.record[1].sum()) > 0     # evidence was recorded
    # the checkpoint keeps the record, so that a resumed run does not start it over
    saved = torch.load(tmp_path / "run" / "checkpoints" / "latest.pt", weights_only=False)["extra"]["metal_record"]
    assert torch.equal(saved["metal"], seen.record[0]) and torch.equal(saved["confidence"], seen.record[1])

    class Resumed(TrainHooks):
        first = None

        def before_step(self, run, step):
            if self.first is None:
                self.first = (run.metal_record.metal.clone(), run.metal_record.confidence.clone())

    cfg.train.iters = 8
    fit(scene, tmp_path / "run", cfg, device="cpu", resume=True, hooks=[resumed := Resumed()])
    assert torch.equal(resumed.first[0], saved["metal"]) and torch.equal(resumed.first[1], saved["confidence"])
    cfg.train.iters = 6
    # with the lobe off (a diffuse scene, or the rule dropped it) the metallic is not shaded: no evidence
    Seen.rows = []
    cfg.render.specular = False
    fit(scene, tmp_path / "run_diffuse", cfg, device="cpu", hooks=[Seen()])
    assert Seen.rows and all(m == 0 and v == 0 for m, v in Seen.rows)
