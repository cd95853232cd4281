"""Global point emitters with traced shadows (nepf_core.fields.emitters): value tests on analytic scenes."""

from __future__ import annotations

import math

import pytest
import torch

from nepf_core import bsdf
from nepf_core.fields.emitters import DARK_SHARE, PLACE_FACTOR, TracedEmitters, dark_under_emitters, dominant, received
from nepf_core.model import ModelConfig, NePFModel
from nepf_core.render.renderer import RenderConfig
from nepf_core.render.shading import Shading, shade_points
from nepf_core.train.setup import param_groups


def _sphere_sdf(centre, radius):
    c = torch.tensor(centre)
    return lambda x: (x - c).norm(dim=-1) - radius


def _fibonacci_sphere(n: int) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float32) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    r = (1 - z * z).sqrt()
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def test_inverse_square_irradiance_and_directions():
    em = TracedEmitters(2)
    with torch.no_grad():
        em.positions.copy_(torch.tensor([[0.0, 0.0, 4.0], [3.0, 0.0, 0.0]]))
        em.log_intensity.copy_(torch.log(torch.tensor([32.0, 9.0])))
    x = torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
    dirs, e = em.illuminate(x)
    # hand-worked: |p0 - x0| = 2 -> 32 / 4; |p1 - x0|^2 = 9 + 4 = 13 -> 9 / 13
    assert torch.allclose(e[0], torch.tensor([8.0, 9.0 / 13.0]))
    assert torch.allclose(e[1], torch.tensor([32.0 / 17.0, 9.0 / 4.0]))
    assert torch.allclose(dirs[0, 0], torch.tensor([0.0, 0.0, 1.0]))
    assert torch.allclose(dirs[1, 1], torch.tensor([1.0, 0.0, 0.0]))
    vis = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    _, e_vis = em.illuminate(x, visibility=vis)
    assert torch.equal(e_vis, e * vis)


def test_dominant_picks_the_most_irradiance_times_cosine():
    dirs = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]])
    n = torch.tensor([[0.0, 0.0, 1.0]])
    l, i = dominant(dirs, torch.tensor([[1.0, 5.0]]), n)   # the second light is at 90 deg: cos 0
    assert torch.equal(l[0], dirs[0, 0]) and float(i) == 1.0


def test_traced_visibility_sees_an_occluder():
    # a unit sphere at the origin and a small sphere between it and the emitter at +z
    big, small = _sphere_sdf((0.0, 0.0, 0.0), 0.5), _sphere_sdf((0.0, 0.0, 0.8), 0.1)
    sdf = lambda x: torch.minimum(big(x), small(x))
    em = TracedEmitters(2)
    with torch.no_grad():
        em.positions.copy_(torch.tensor([[0.0, 0.0, 5.0], [5.0, 0.0, 0.0]]))
    x = torch.tensor([[0.0, 0.0, 0.5], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0]])
    n = x / x.norm(dim=-1, keepdim=True)
    vis = em.trace_visibility(sdf, x, n)
    # the top point is shadowed from +z by the small sphere and sees +x; the +x point sees +x,
    # and the +z emitter grazes past the small sphere; the +y point's ray to +x leaves the big sphere
    assert vis[0].tolist() == [0.0, 1.0]
    assert vis[1].tolist() == [1.0, 1.0]
    assert vis[2, 1] == 1.0


def test_batched_shadow_rays_match_one_fine_march_per_emitter():
    # three emitters around a sphere with two blockers (all thicker than the shadow rays' coarser
    # minimum step): the one-batch march must give each point-emitter pair the answer of a fine,
    # long march of that pair alone (the relight's tracer), in the [N, K] order
    from nepf_core.relight.tracing import TraceConfig, light_visibility
    parts = [_sphere_sdf((0.0, 0.0, 0.0), 0.5), _sphere_sdf((0.0, 0.0, 0.8), 0.15), _sphere_sdf((0.75, 0.3, 0.0), 0.1)]
    sdf = lambda x: torch.stack([f(x) for f in parts]).amin(0)
    em = TracedEmitters(3)
    with torch.no_grad():
        em.positions.copy_(torch.tensor([[0.0, 0.0, 4.0], [4.0, 1.6, 0.0], [-1.0, -3.0, 1.0]]))
    n = _fibonacci_sphere(400)
    x = 0.5 * n
    vis = em.trace_visibility(sdf, x, n)
    fine = TraceConfig(max_steps=2048, min_step=1e-4, shadow_offset=2e-2)
    ref = torch.stack([light_visibility(sdf, x, n, p, fine) for p in em.positions.detach()], -1)
    assert vis.shape == (400, 3)
    assert 0.1 < float((1 - ref).mean()) < 0.9 and 0 < float((1 - ref[:, 0]).sum()) != float((1 - ref[:, 1]).sum())
    assert torch.equal(vis, ref)


def test_shading_sums_one_bsdf_term_per_visible_emitter():
    torch.manual_seed(0)
    model = NePFModel(ModelConfig(sdf_kind="grid", light="emitters", emitters=2))
    cfg = RenderConfig(bsdf_kind="gltf")
    N = 16
    x = 0.3 * torch.randn(N, 3)
    n = torch.nn.functional.normalize(torch.randn(N, 3), dim=-1)
    v = torch.nn.functional.normalize(torch.randn(N, 3), dim=-1)
    _, f = model.sdf(x)
    vis = (torch.rand(N, 2) > 0.5).float()
    p = shade_points(model, cfg, Shading(), x, v, n, f, None, visibility=vis)
    dirs, e = model.photon.illuminate(x, visibility=vis)
    albedo, rough, metal = model.material(x, n, f)
    expected = sum(bsdf.shade(n, dirs[:, k], -v, albedo, rough[:, None], metal[:, None], e[:, k, None],
                              kind="gltf") for k in range(2))
    assert torch.allclose(p.pbr, expected, atol=1e-6)
    hidden = vis.sum(-1) == 0
    assert torch.all(p.pbr[hidden] == 0)


def test_place_starts_at_the_cameras_farthest_apart_and_keeps_the_irradiance():
    em = TracedEmitters(2)
    before = (em.log_intensity.exp() / (em.positions ** 2).sum(-1)).sum()
    cams = torch.tensor([[3.0, 0.0, 0.0], [0.0, 3.0, 0.1], [-3.0, 0.2, 0.0], [2.9, 0.5, 0.0]])
    em.place(cams)
    # the first: nearest the cameras' mean (0.725, 0.925, 0.025) is camera 1; the second: farthest from it
    d = torch.cdist(cams, cams[1:2])[:, 0]
    assert torch.allclose(em.positions[0], cams[1] * PLACE_FACTOR)
    assert torch.allclose(em.positions[1], cams[int(d.argmax())] * PLACE_FACTOR)
    after = (em.log_intensity.exp() / (em.positions ** 2).sum(-1)).sum()
    assert torch.isclose(before, after, rtol=1e-5)


def test_emitters_learn_at_their_own_rate():
    model = NePFModel(ModelConfig(sdf_kind="grid", light="emitters", emitters=1))
    groups = param_groups(model, 1e-3, 1e-2)
    own = [g for g in groups if any(p is model.photon.positions for p in g["params"])]
    assert len(own) == 1 and own[0]["lr"] == pytest.approx(1e-3 * model.photon.lr_scale)
    assert {id(p) for p in own[0]["params"]} == {id(model.photon.positions), id(model.photon.log_intensity)}
    n_all = sum(len(g["params"]) for g in groups)
    assert n_all == len(list(model.parameters()))
    with pytest.raises(ValueError, match="unknown light model"):
        NePFModel(ModelConfig(sdf_kind="grid", light="emitters_residual"))


def test_a_point_light_is_recovered_from_a_lambertian_sphere():
    """The lit half of a white Lambertian sphere under a point light at ``p*``: fitting one
    emitter's position and intensity to the shading finds the light within 2 deg."""
    torch.manual_seed(0)
    p_true, i_true = torch.tensor([2.0, -1.5, 3.0]), 40.0
    n = _fibonacci_sphere(2000)
    x = 0.5 * n
    l = torch.nn.functional.normalize(p_true - x, dim=-1)
    albedo = torch.full((len(x), 3), 0.6)
    target = albedo / math.pi * i_true / ((p_true - x) ** 2).sum(-1, keepdim=True) * (n * l).sum(-1, keepdim=True).clamp_min(0)
    em = TracedEmitters(1)
    em.place(torch.tensor([[0.0, 3.0, 0.0]]))   # a camera 90 deg from the light
    opt = torch.optim.Adam(em.parameters(), lr=0.05)
    for _ in range(600):
        dirs, e = em.illuminate(x)
        pred = albedo / math.pi * e[:, :1] * (n * dirs[:, 0]).sum(-1, keepdim=True).clamp_min(0)
        loss = (pred - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    p = em.positions.detach()[0]
    angle = math.degrees(math.acos(float(torch.nn.functional.cosine_similarity(p, p_true, dim=0))))
    assert angle < 2.0


def test_secondary_emitters_start_at_their_share():
    from nepf_core.fields.emitters import SECONDARY_SHARE
    em = TracedEmitters(3)
    em.set_init_intensity(4.0)
    at_origin = em.log_intensity.exp() / (em.positions ** 2).sum(-1)
    assert torch.allclose(at_origin, torch.tensor([4.0 * (1 - 2 * SECONDARY_SHARE), 4.0 * SECONDARY_SHARE,
                                                   4.0 * SECONDARY_SHARE]), rtol=1e-5)
    with pytest.raises(ValueError, match="finite and > 0"):
        em.set_init_intensity(0.0)


def test_place_lights_starts_the_emitters_from_the_images(small_scene):
    from nepf_core.rays import foreground_peaks
    from nepf_core.train.setup import EMITTER_START_ALBEDO, place_lights
    model = NePFModel(ModelConfig(sdf_kind="grid", light="emitters", emitters=2))
    place_lights(model, small_scene)
    q99 = float(torch.quantile(torch.as_tensor(foreground_peaks(small_scene.images, small_scene.masks)), 0.99))
    at_origin = (model.photon.log_intensity.exp() / (model.photon.positions ** 2).sum(-1)).sum().detach()
    assert float(at_origin) == pytest.approx(math.pi * q99 / EMITTER_START_ALBEDO, rel=1e-4)
    centres = torch.as_tensor(small_scene.c2w[:, :3, 3])
    d = torch.cdist(model.photon.positions.detach() / PLACE_FACTOR, centres.float()).min(-1).values
    assert torch.all(d < 1e-5)   # each emitter starts at a camera centre, pushed out


def test_dark_under_emitters_is_relative_to_the_q90_of_what_the_points_receive():
    n = torch.tensor([[0.0, 0.0, 1.0]]).expand(12, 3)
    dirs = torch.zeros(12, 2, 3)
    dirs[:, 0] = torch.tensor([0.0, 0.0, 1.0])                # head-on
    dirs[:, 1] = torch.tensor([0.0, 0.6, -0.8])               # from behind: delivers nothing
    e = torch.ones(12, 2)
    e[0, 0], e[1, 0], e[2, 0], e[11, 0] = 0.0, 0.01, 0.03, 100.0
    got = received(dirs, e, n)
    assert torch.allclose(got[:, 1], torch.zeros(12)) and torch.allclose(got[:, 0], e[:, 0])
    among = torch.ones(12, dtype=torch.bool)
    among[11] = False                                         # the outlier is not among the reference points
    dark = dark_under_emitters(dirs, e, n, among=among)       # q90 over the 11 is 1: dark below DARK_SHARE
    assert DARK_SHARE == pytest.approx(0.02)
    assert dark.tolist() == [True, True] + [False] * 10
    assert dark_under_emitters(dirs, e, n, among=torch.zeros(12, dtype=torch.bool)).all()   # nothing to compare


def test_a_dark_pixel_trains_the_albedo_under_a_traced_light_and_not_in_a_traced_shadow():
    """Two points, both with an unlit (dark) training pixel: one sees the emitters (a black
    texture under light), one is in their traced shadow. Only the first one's colour error
    reaches the albedo; the photon network's rule (no visibility) stops both."""
    torch.manual_seed(0)
    model = NePFModel(ModelConfig(sdf_kind="grid", light="emitters", emitters=2))
    cfg = RenderConfig(bsdf_kind="gltf", unlit_albedo_stopgrad=True)
    N = 64
    x = 0.2 * torch.randn(N, 3)
    n = torch.nn.functional.normalize(model.photon.positions.detach()[0] - x, dim=-1)   # facing emitter 0
    v = -n
    f = model.sdf(x)[1].detach()
    unlit = torch.zeros(N, dtype=torch.bool)
    unlit[:2] = True
    vis = torch.ones(N, 2)
    vis[1] = 0.0                                              # point 1 is in both emitters' shadow

    def albedo_grad(visibility):
        model.zero_grad()
        p = shade_points(model, cfg, Shading(), x, v, n, f, unlit, visibility=visibility)
        albedo = p.albedo
        albedo.retain_grad()
        p.pbr[:2].sum().backward()
        return albedo.grad

    g = albedo_grad(vis)
    assert g[0].abs().sum() > 0                               # a black texture under light: it trains
    assert torch.all(g[1] == 0)                               # a shadow: it does not
    g = albedo_grad(None)
    assert torch.all(g[:2] == 0)                              # without traced shadows the pixel decides


def test_unlit_points_take_the_lit_mean_albedo_only_where_no_light_reaches():
    """``loss_albedo_fill`` by hand: two bright lit rays (albedo mean (0.3, 0.4, 0.5)), one
    shadowed ray, one dark pixel under the light (a black texture: left alone) and a ray off the
    surface: the loss is ``|c_shadowed - mean| / 4 surface rays`` and only the shadowed ray moves."""
    from types import SimpleNamespace

    from nepf_core.losses.material import loss_albedo_fill
    albedo = torch.tensor([[0.2, 0.4, 0.6], [0.4, 0.4, 0.4], [0.9, 0.1, 0.5], [0.05, 0.05, 0.05], [0.5, 0.5, 0.5]],
                          requires_grad=True)
    n = torch.tensor([[0.0, 0.0, 1.0]]).expand(5, 3)
    dirs = torch.tensor([0.0, 0.0, 1.0]).expand(5, 1, 3)
    e = torch.tensor([[1.0], [1.0], [0.0], [1.0], [1.0]])     # ray 2 is in the traced shadow
    surface = SimpleNamespace(albedo=albedo, normal=n, lights=(dirs, e))
    b = SimpleNamespace(out=SimpleNamespace(surface=surface), zero=torch.zeros(()),
                        on_surf=torch.tensor([True, True, True, True, False]),
                        lit=torch.tensor([True, True, False, False, False]))
    loss = loss_albedo_fill(b)
    assert float(loss.detach()) == pytest.approx((0.6 + 0.3 + 0.0) / 3 / 4)
    loss.backward()
    assert albedo.grad[2].abs().sum() > 0
    assert torch.all(albedo.grad[[0, 1, 3, 4]] == 0)
    surface.lights = None
    with pytest.raises(ValueError, match="w_albedo_fill > 0 needs model.light"):
        loss_albedo_fill(b)


def test_the_fill_prior_needs_the_traced_emitters():
    from nepf_core.config import preset
    cfg = preset("fast")
    cfg.check()
    cfg.model.light = "photon"
    with pytest.raises(ValueError, match="w_albedo_fill > 0 needs model.light"):
        cfg.check()
