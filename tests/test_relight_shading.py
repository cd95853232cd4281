"""Relighting on analytic scenes: a flat lit patch against an independent glTF reference, the
shadow tracer, and the change of frame of the lights."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from nepf_core.data.scene import Scene
from nepf_core.rays import PixelSampler
from nepf_core.relight.lights import (LightsError, PointLights, canonical_lights, horizontal_axes,
                                      lights_to_normalised, load_lights, parse_lights)
from nepf_core.relight.render import query_surfaces, relight_views
from nepf_core.relight.shade import ShadeOptions
from nepf_core.relight.tracing import TraceConfig, light_visibility

ALBEDO, ROUGH, METAL = (0.7, 0.4, 0.2), 0.4, 0.3


def gltf_reference(n, l, v, c, r, m):
    """glTF 2.0 Appendix B written out from the specification (numpy, float64), with the project's
    documented roughness floor a = 1e-3 + 0.999 r^2."""
    n, l, v, c = (np.asarray(t, np.float64) for t in (n, l, v, c))
    h = (l + v) / np.linalg.norm(l + v)
    nl, nv, nh, vh = n @ l, n @ v, n @ h, abs(v @ h)
    a = 1e-3 + 0.999 * r * r
    f0 = 0.04 * (1 - m) + c * m
    F = f0 + (1 - f0) * (1 - vh) ** 5
    c_diff = c * (1 - m)
    D = a * a / (math.pi * (nh * nh * (a * a - 1) + 1) ** 2)
    G = (2 * nl / (nl + math.sqrt(a * a + (1 - a * a) * nl * nl))) * (2 * nv / (nv + math.sqrt(a * a + (1 - a * a) * nv * nv)))
    return (1 - F) * c_diff / math.pi + F * D * G / (4 * nl * nv)


class Patch:
    """FieldQuery of a slab ``-0.2 <= z <= 0`` (top face the patch, normal +z), constant material,
    optionally with a sphere occluder."""

    def __init__(self, occluder=None):
        self.occluder = occluder

    def sdf(self, x):
        f = torch.maximum(x[:, 2], -x[:, 2] - 0.2)
        if self.occluder is not None:
            c, r = self.occluder
            f = torch.minimum(f, (x - torch.tensor(c)).norm(dim=-1) - r)
        return f

    def normal(self, x):
        n = torch.zeros_like(x)
        n[:, 2] = 1.0
        return n

    def material(self, x, n):
        return (torch.tensor(ALBEDO).expand(x.shape[0], 3), torch.full((x.shape[0],), ROUGH),
                torch.full((x.shape[0],), METAL))


def top_camera(size=5, height=0.8, focal=20.0) -> Scene:
    """One camera at (0, 0, height) looking down -z; the centre pixel's ray is exactly -z."""
    c2w = np.eye(4, dtype=np.float32)
    c2w[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
    c2w[:3, 3] = [0, 0, height]
    K = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], np.float32)
    return Scene(images=np.zeros((1, size, size, 3), np.float32), masks=None, intrinsics=K[None], c2w=c2w[None],
                 world_from_norm=np.eye(4), names=["v0"])


def relight_centre(query, light_dir, intensity=3.0, dist=2.0, shadows=True):
    """The centre pixel's one ray through its centre (``subsamples=1``): exactly the -z ray."""
    sampler = PixelSampler(top_camera(), "cpu")
    pos = np.asarray(light_dir, np.float64) * dist
    trace = TraceConfig(hit_eps=1e-6, min_step=1e-7)   # the hit point within 1e-6 of the surface
    rgb, alpha = relight_views(query_surfaces(query, trace), query.sdf, sampler, pos[None],
                               np.full((1, 3), intensity), ShadeOptions(kind="gltf"), shadows=shadows,
                               subsamples=1)
    return rgb[0, 0, 2, 2], alpha[0, 2, 2]


class HalfPatch(Patch):
    """The patch cut at ``x = edge``: the box ``x <= edge, -0.2 <= z <= 0`` (unbounded in y)."""

    def __init__(self, edge):
        super().__init__()
        self.edge = edge

    def sdf(self, x):
        q = torch.stack([x[:, 0] - self.edge, -x[:, 2] - 0.1], -1)
        q = torch.stack([q[:, 0], q[:, 1].abs() - 0.1], -1)   # box half-width 0.1 in z around -0.1
        return q.clamp_min(0.0).norm(dim=-1) + q.amax(-1).clamp_max(0.0)


def test_a_pixel_the_silhouette_cuts_averages_its_subpixels():
    """The top camera (focal 20 px, 0.8 above the patch): the centre pixel spans x in [-0.02, 0.02]
    and its 2 x 2 sub-pixel rays meet the plane at x = -0.01 and +0.01. With the patch's edge at
    x = 0.005 two of the four hit, at (-0.01, +-0.01, 0): coverage 1/2 and a quarter of the sum of
    those two points' glTF shading (the reference above). One ray through the centre calls the
    pixel fully covered."""
    sampler = PixelSampler(top_camera(), "cpu")
    trace = TraceConfig(hit_eps=1e-6, min_step=1e-7)
    q = HalfPatch(0.005)
    run = lambda n: relight_views(query_surfaces(q, trace), q.sdf, sampler, np.array([[0.0, 0.0, 2.0]]),
                                  np.full((1, 3), 3.0), ShadeOptions(kind="gltf"), subsamples=n)
    rgb, alpha = run(2)
    assert alpha[0, 2, 2] == 0.5 and alpha[0, 2, 1] == 1.0 and alpha[0, 2, 3] == 0.0
    assert (alpha[0, :, 2] == 0.5).all()                                    # the whole column
    light, cam = np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, 0.8])
    want = 0.0
    for y in (-0.01, 0.01):
        x = np.array([-0.01, y, 0.0])
        l, v = light - x, cam - x
        d2 = l @ l
        l, v = l / np.sqrt(d2), v / np.linalg.norm(v)
        want = want + gltf_reference([0, 0, 1], l, v, ALBEDO, ROUGH, METAL) * 3.0 * l[2] / d2 / 4
    np.testing.assert_allclose(rgb[0, 0, 2, 2], want, rtol=1e-4)
    assert rgb[0, 0, 2, 3].max() == 0.0
    rgb1, alpha1 = run(1)
    assert alpha1[0, 2, 2] == 1.0


def test_only_the_silhouette_pixels_take_the_subpixel_rays():
    """The half patch of the test above: the centre rays of columns 0-2 hit (x = -0.08, -0.04, 0),
    of 3-4 miss, so columns 2 and 3 (10 pixels) have both in their 3 x 3 neighbourhood; the
    render casts 25 centre rays and 4 x 10 sub-pixel rays, and the interior keeps its centre ray."""
    sampler = PixelSampler(top_camera(), "cpu")
    q = HalfPatch(0.005)
    inner = query_surfaces(q, TraceConfig(hit_eps=1e-6, min_step=1e-7))
    seen = []

    def counting(rays):
        seen.append(len(rays))
        return inner(rays)
    light = (np.array([[0.0, 0.0, 2.0]]), np.full((1, 3), 3.0), ShadeOptions(kind="gltf"))
    rgb, alpha = relight_views(counting, q.sdf, sampler, *light)
    assert sum(seen) == 25 + 4 * 10
    rgb1, _ = relight_views(inner, q.sdf, sampler, *light, subsamples=1)
    np.testing.assert_array_equal(rgb[:, :, :, :2], rgb1[:, :, :, :2])     # columns 0-1: the centre ray


@pytest.mark.parametrize("theta_deg", [0.0, 45.0])
def test_flat_patch_matches_the_gltf_reference(theta_deg):
    # tolerance: relative 1e-5 (float32 against float64; the traced point is within 1e-6 of z = 0).
    # The GLB itself stores the material in 8 bits (sRGB base colour, linear roughness / metallic),
    # which adds up to 0.5/255 per channel (sRGB) on top of this in what three.js shows.
    t = math.radians(theta_deg)
    l = np.array([math.sin(t), 0.0, math.cos(t)])
    got, alpha = relight_centre(Patch(), l)
    assert alpha == 1.0
    f = gltf_reference([0, 0, 1], l, [0, 0, 1], ALBEDO, ROUGH, METAL)
    want = f * 3.0 * max(l[2], 0.0) / 2.0 ** 2
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert got.min() > 0.005


def test_a_sphere_between_patch_and_light_casts_a_shadow():
    # the occluder sits on the segment from the centre pixel's surface point (origin) to a light
    # at 45 deg, off the camera's centre ray (its centre is 0.3 from the z axis, radius 0.1)
    l = np.array([math.sin(math.pi / 4), 0.0, math.cos(math.pi / 4)])
    lit, _ = relight_centre(Patch(), l)
    shadowed, alpha = relight_centre(Patch(occluder=((0.3, 0.0, 0.3), 0.1)), l)
    assert alpha == 1.0 and lit.min() > 0.01
    assert np.all(shadowed == 0.0)
    unshadowed, _ = relight_centre(Patch(occluder=((0.3, 0.0, 0.3), 0.1)), l, shadows=False)
    np.testing.assert_allclose(unshadowed, lit, rtol=1e-5)


def test_shadow_tracer_on_analytic_cases():
    q = Patch(occluder=((0.0, 0.0, 0.5), 0.1))
    x = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.0]])
    n = torch.tensor([[0.0, 0.0, 1.0]]).expand(4, 3)
    lights = torch.tensor([[0.0, 0.0, 0.9], [0.5, 0.0, 0.9], [0.0, 0.3, 0.9], [0.0, 0.0, 0.3]])
    vis = torch.stack([light_visibility(q.sdf, x[i:i + 1], n[i:i + 1], lights[i], TraceConfig())[0]
                       for i in range(4)])
    # straight up through the sphere: shadowed; beside it: lit; the ray grazing it at distance
    # 0.3 > 0.1 from its centre: lit; the light below the sphere (segment ends first): lit
    assert vis.tolist() == [0.0, 1.0, 1.0, 1.0]


def test_lights_to_normalised_keeps_the_irradiance():
    # world_from_norm = [s R | t]: a point at p_n and a light at l_n in the normalised frame sit at
    # M p_n, M l_n in the world, d_w = s d_n; E_w = I_w / d_w^2 must equal E_n = I_n / d_n^2
    s, ang = 2.5, math.radians(30)
    R = np.array([[math.cos(ang), -math.sin(ang), 0], [math.sin(ang), math.cos(ang), 0], [0, 0, 1]])
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = s * R, [3.0, -1.0, 0.5]
    world = PointLights(np.array([[10.0, 2.0, -4.0]]), np.array([[50.0, 25.0, 5.0]]))
    ln = lights_to_normalised(world, M)
    np.testing.assert_allclose(M[:3, :3] @ ln.positions[0] + M[:3, 3], world.positions[0], atol=1e-12)
    np.testing.assert_allclose(ln.intensities[0], [8.0, 4.0, 0.8], rtol=1e-12)        # I / 6.25
    p_n = np.array([0.1, 0.2, -0.3])
    p_w = M[:3, :3] @ p_n + M[:3, 3]
    e_w = world.intensities[0] / np.sum((world.positions[0] - p_w) ** 2)
    e_n = ln.intensities[0] / np.sum((ln.positions[0] - p_n) ** 2)
    np.testing.assert_allclose(e_n, e_w, rtol=1e-10)


def test_malformed_lights_name_the_file_and_the_light(tmp_path):
    good = {"lights": [{"type": "point", "position_world": [1, 2, 3], "intensity_rgb": [1, 1, 1],
                        "position_normalized": "ignored", "units": "ignored"}]}
    assert len(parse_lights(good)) == 1
    cases = [
        ({"lights": []}, "'lights' is empty"),
        ({"light": []}, "expected an object with a 'lights' list"),
        ({"lights": [good["lights"][0], {"type": "spot", "position_world": [0, 0, 0], "intensity_rgb": [1, 1, 1]}]},
         'light 1: \'type\' must be "point"'),
        ({"lights": [{"type": "point", "position_world": [0, 0], "intensity_rgb": [1, 1, 1]}]},
         "light 0: 'position_world' must be a list of 3 finite numbers"),
        ({"lights": [{"type": "point", "position_world": [0, 0, 0]}]}, "light 0: missing 'intensity_rgb'"),
        ({"lights": [{"type": "point", "position_world": [0, 0, 0], "intensity_rgb": [1, -1, 1]}]},
         "light 0: 'intensity_rgb' must be >= 0"),
        ({"lights": [{"type": "point", "position_world": [0, "x", 0], "intensity_rgb": [1, 1, 1]}]},
         "light 0: 'position_world' must be a list of 3"),
    ]
    for data, msg in cases:
        p = tmp_path / "my_lights.json"
        p.write_text(json.dumps(data))
        with pytest.raises(LightsError, match="^my_lights.json: ") as e:
            load_lights(p)
        assert msg in str(e.value) and str(tmp_path) not in str(e.value)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(LightsError, match="bad.json: not valid JSON"):
        load_lights(tmp_path / "bad.json")
    # issue 37: the one bounded parser (nepf_json); the file and the limit are named
    light = '{"type": "point", "position_world": [0, 0, 3], "intensity_rgb": [1, 1, 1]}'
    for text, words in (('{"lights": [' + light + '], "x": ' + "[" * 2000 + "]" * 2000 + "}", ("nesting", "32")),
                        ('{"lights": [], "lights": [' + light + "]}", ('"lights"', "twice")),
                        ('{"lights": [' + light.replace("3]", "1" + "0" * 5000 + "]") + "]}", ("number", "100"))):
        (tmp_path / "limits.json").write_text(text)
        with pytest.raises(LightsError, match="^limits.json: ") as e:
            load_lights(tmp_path / "limits.json")
        assert all(w in str(e.value) for w in words), str(e.value)


def test_canonical_lights_geometry():
    c, R = np.array([0.15, -0.1, 0.05]), 1.2
    # azimuth 0 is the viewer's: +Z in the GLB's +Y-up frame, i.e. R^T e_z in the world (-y for a +Z-up world)
    for up, ax in (((0, 0, 1), (0, -1, 0)), ((0, 1, 0), (0, 0, 1)), ((0, -1, 0), (0, 0, 1))):
        L = canonical_lights(c, R, up)
        rel = L.positions - c
        np.testing.assert_allclose(np.linalg.norm(rel, axis=-1), 3 * R, rtol=1e-12)
        np.testing.assert_allclose(rel @ np.asarray(up, float) / (3 * R), math.sin(math.pi / 4), rtol=1e-12)
        # azimuth 0 lies along the viewer's x-like axis; the three are 120 degrees apart
        np.testing.assert_allclose(rel[0] @ np.asarray(ax, float) / (3 * R), math.cos(math.pi / 4), rtol=1e-12)
        flat = rel - np.outer(rel @ np.asarray(up, float), up)
        cosang = flat[0] @ flat[1] / (np.linalg.norm(flat[0]) * np.linalg.norm(flat[1]))
        assert cosang == pytest.approx(-0.5, abs=1e-12)
        np.testing.assert_allclose(L.intensities / (3 * R) ** 2, 2.0, rtol=1e-12)
    ax, ay = horizontal_axes((1.0, 1.0, 0.0))
    u = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    assert abs(ax @ u) < 1e-12 and abs(ay @ u) < 1e-12 and abs(ax @ ay) < 1e-12


def test_the_subpixel_grid_is_stratified_over_the_pixel():
    from nepf_core.render.antialias import subpixel_points
    assert subpixel_points(1) == [(0.5, 0.5)]
    pts = np.array(subpixel_points(3))
    assert len(pts) == 9 and len({tuple(p) for p in pts}) == 9
    np.testing.assert_allclose(pts.mean(0), [0.5, 0.5])                     # centred on the pixel
    np.testing.assert_allclose(np.unique(pts[:, 0]), [1 / 6, 0.5, 5 / 6])    # one per sub-pixel column
    with pytest.raises(ValueError, match="at least 1"):
        subpixel_points(0)
