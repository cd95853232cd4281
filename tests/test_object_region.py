"""The object region of captures without masks (issue 26): sparse points triangulated from the
images (nepf_core/data/sparse_points.py), the support plane found among them
(nepf_core/data/object_region.py), the renderer's ray segment ended at it and the background
started there (render/sampling.py, fields/background.py), and the export's SDF cut to it
(model.ModelFieldQuery).

The scene is analytic: a ball mounted on a wall (the fox's case), both with a solid noise
texture, ray-cast exactly, seen by look-at cameras from the front.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy import ndimage

from nepf_core.data.object_region import RegionConfig, find_object_region, find_support_plane
from nepf_core.data.scene import Scene
from nepf_core.data.sparse_points import fundamental, midpoint_triangulation, sampson_distance, triangulate_scene
from nepf_core.data.synth import look_at
from nepf_core.export.mesh import extract_mesh, remove_floaters
from nepf_core.model import ModelFieldQuery
from nepf_core.render.sampling import halfspace_exit, object_segment

BALL_CENTRE = np.array([0.0, 0.0, 0.2])
BALL_RADIUS = 0.4
WALL_Z = -0.15  # the wall fills z < WALL_Z; the ball sticks out of it towards +z


def ball_on_wall_sdf(x: torch.Tensor) -> torch.Tensor:
    """Union of the ball and the solid wall ``z < WALL_Z`` (exact distance outside both)."""
    ball = torch.linalg.vector_norm(x - torch.as_tensor(BALL_CENTRE, dtype=x.dtype), dim=-1) - BALL_RADIUS
    return torch.minimum(ball, x[:, 2] - WALL_Z)


def front_cameras(n: int, distance: float = 2.2, size: int = 128, fov_deg: float = 45.0):
    """Look-at cameras at the origin on a cone of 40 deg about +z (all in front of the wall)."""
    k = np.arange(n) + 0.5
    z = 1.0 - k / n * (1.0 - math.cos(math.radians(40)))
    r = np.sqrt(1.0 - z * z)
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    eyes = distance * np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    c2w = np.stack([look_at(e, np.zeros(3), up=(0.0, 1.0, 0.0)) for e in eyes])
    f = 0.5 * size / math.tan(math.radians(fov_deg / 2))
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    return np.repeat(K[None], n, 0), c2w


def solid_texture(p: np.ndarray, seed: int = 0) -> np.ndarray:
    """Value noise (trilinear on a random 48^3 lattice over [-1.2, 1.2]^3): ``[M, 3] -> [M]`` in [0, 1]."""
    lattice = np.random.default_rng(seed).random((48, 48, 48))
    idx = (np.clip(p, -1.2, 1.2) + 1.2) / 2.4 * 47
    return ndimage.map_coordinates(lattice, idx.T, order=1)


def render_ball_on_wall(n_views: int = 12, size: int = 128) -> Scene:
    """Exact ray casting of the ball and the wall plane; colour = solid texture at the hit."""
    K, c2w = front_cameras(n_views, size=size)
    v, u = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="ij")
    images = []
    for Ki, pose in zip(K, c2w):
        d = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], -1) @ np.linalg.inv(Ki).T @ pose[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = pose[:3, 3]
        t_wall = (WALL_Z - o[2]) / np.where(d[:, 2] < 0, d[:, 2], -1e-9)
        oc = o - BALL_CENTRE
        b = d @ oc
        disc = b * b - (oc @ oc - BALL_RADIUS ** 2)
        t_ball = np.where(disc > 0, -b - np.sqrt(np.clip(disc, 0, None)), np.inf)
        t = np.minimum(np.where(t_ball > 0, t_ball, np.inf), t_wall)
        g = solid_texture(o + t[:, None] * d)
        images.append(np.repeat(g.reshape(size, size, 1), 3, -1).astype(np.float32))
    return Scene(images=np.stack(images), masks=None, intrinsics=K.astype(np.float32), c2w=c2w.astype(np.float32),
                 world_from_norm=np.eye(4), names=[f"{i}.png" for i in range(n_views)])


def surface_distance(p: np.ndarray) -> np.ndarray:
    """Distance of points to the ball-on-wall surface (the union's exact SDF, absolute)."""
    return np.abs(ball_on_wall_sdf(torch.as_tensor(p)).numpy())


@pytest.fixture(scope="module")
def ball_on_wall() -> Scene:
    return render_ball_on_wall()


def test_epipolar_and_triangulation_hand_worked():
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    a, b = np.eye(4), np.eye(4)
    b[0, 3] = 1.0  # camera j one unit to the right, same orientation
    X = np.array([[0.2, -0.1, 4.0]])
    uv_a = X[:, :2] / X[:, 2:] * 100 + 50          # (55, 47.5)
    uv_b = (X[:, :2] - [1.0, 0.0]) / X[:, 2:] * 100 + 50
    F = fundamental(K, a, K, b)
    assert sampson_distance(F, uv_a, uv_b)[0] == pytest.approx(0.0, abs=1e-9)
    # a match 3 px off its epipolar line (the horizontal row v = 47.5) is 3 px away by the first-order distance:
    # with F = [[0,0,0],[0,0,-c],[0,c,0]] the residual is c * 3 and the gradient norm sqrt(2) c
    assert sampson_distance(F, uv_a, uv_b + [0.0, 3.0])[0] == pytest.approx(3.0 / math.sqrt(2.0), rel=1e-6)
    da = (np.c_[uv_a, [1.0]] @ np.linalg.inv(K).T)
    db = (np.c_[uv_b, [1.0]] @ np.linalg.inv(K).T)
    pts, ok = midpoint_triangulation(a[:3, 3][None], da / np.linalg.norm(da), b[:3, 3][None],
                                     db / np.linalg.norm(db), 1.0)
    assert ok[0] and np.allclose(pts, X, atol=1e-9)
    # the same ray twice: no angle, no depth
    _, ok = midpoint_triangulation(a[:3, 3][None], da / np.linalg.norm(da), a[:3, 3][None] + 1e-3,
                                   da / np.linalg.norm(da), 1.0)
    assert not ok[0]


def test_triangulated_points_lie_on_the_surfaces(ball_on_wall):
    pts = triangulate_scene(ball_on_wall)
    assert len(pts) > 300
    d = surface_distance(pts)
    assert np.median(d) < 0.01
    assert (d < 0.03).mean() > 0.9  # the RANSAC inlier distance


def test_the_wall_is_found_before_training(ball_on_wall):
    region = find_object_region(ball_on_wall)
    assert region.support_normal is not None, region.reason
    n = np.asarray(region.support_normal)
    # the wall is z = WALL_Z with its normal towards the cameras (+z): s(x) = z - WALL_Z
    assert n[2] > math.cos(math.radians(2.0))
    assert region.support_offset == pytest.approx(-WALL_Z, abs=0.01)
    assert region.object_share > 0.05 and region.support_share > 0.2
    hs = region.halfspace()
    assert hs[3] == pytest.approx(region.support_offset - region.margin)


def test_cameras_behind_the_plane_or_nothing_on_it_reject_it():
    rng = np.random.default_rng(1)
    on_plane = np.c_[rng.uniform(-0.5, 0.5, (600, 2)), np.zeros(600)]
    above = np.c_[rng.uniform(-0.2, 0.2, (200, 2)), rng.uniform(0.2, 0.4, 200)]
    cams = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, -3.0]])
    region = find_support_plane(np.r_[on_plane, above], cams)
    assert region.support_normal is None and "both sides" in region.reason
    region = find_support_plane(np.r_[on_plane, above], cams[:1])
    assert region.support_normal is not None
    assert region.support_share == pytest.approx(0.75, abs=0.01)
    assert region.object_share == pytest.approx(0.25, abs=0.01)
    region = find_support_plane(on_plane, cams[:1])
    assert region.support_normal is None and "no object" in region.reason
    # points all round a ball: the best plane band holds far less than a support's share
    ball = rng.normal(size=(2000, 3))
    ball = 0.5 * ball / np.linalg.norm(ball, axis=1, keepdims=True)
    region = find_support_plane(ball, cams[:1], RegionConfig())
    assert region.support_normal is None and "holds" in region.reason


def test_ray_segment_ends_at_the_plane_and_the_background_starts_there():
    hs = (0.0, 0.0, 1.0, 0.5)  # object where z > -0.5
    o = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.0, 0.0, -3.0], [0.0, 0.0, -0.8]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    t = halfspace_exit(o, d, hs)
    # straight down: leaves at z = -0.5, t = 3.5; slanted: 3.5 / 0.8; moving in: never; starting outside: 0
    assert t.tolist() == pytest.approx([3.5, 3.5 / 0.8, math.inf, 0.0])
    near, far, hit, cut = object_segment(o[:1], d[:1], hs)
    assert (near.item(), far.item(), hit.item()) == pytest.approx((2.0, 3.5, True))  # sphere chord [2, 4] cut at 3.5
    near, far, _, cut = object_segment(o[:1], d[:1], None)
    assert far.item() == pytest.approx(4.0) and cut is None

    from nepf_core.fields.background import BackgroundConfig, BackgroundVolume
    bg = BackgroundVolume(BackgroundConfig(n_samples=4))
    starts = []
    bg.sample_distances = lambda t0, **kw: (starts.append(t0.clone()), t0[:, None].expand(-1, 4))[1]
    bg(o[:1], d[:1])
    bg(o[:1], d[:1], start=torch.tensor([3.5]))
    assert starts[0].item() == pytest.approx(4.0) and starts[1].item() == pytest.approx(3.5)


def _field_query(sdf, halfspace) -> ModelFieldQuery:
    model = SimpleNamespace(cfg=SimpleNamespace(object_halfspace=halfspace), query_sdf=sdf)
    return ModelFieldQuery(model)


def test_export_sdf_is_cut_to_the_region_hand_worked():
    q = _field_query(lambda x: torch.full((x.shape[0],), -0.2), (0.0, 0.0, 1.0, 0.4))
    x = torch.tensor([[0.0, 0.0, 0.0],     # n.x + c = 0.4: inside everything, f kept
                      [0.0, 0.0, -0.35],   # 0.05 in front of the cut: still f (-0.2 < -0.05)
                      [0.0, 0.0, -0.5],    # 0.1 behind the cut
                      [0.0, 0.9, 0.9]])    # |x| - 1 = 0.2728: outside the ball
    assert q.sdf(x).tolist() == pytest.approx([-0.2, -0.05, 0.1, math.hypot(0.9, 0.9) - 1.0], abs=1e-6)
    assert _field_query(lambda x: torch.full((x.shape[0],), -0.2), None).sdf(x).tolist() == pytest.approx([-0.2] * 4)


def test_the_cut_mesh_is_the_ball_alone(ball_on_wall):
    region = find_object_region(ball_on_wall)
    uncut = extract_mesh(ball_on_wall_sdf, 64, (-1.0, 1.0))
    cut = extract_mesh(_field_query(ball_on_wall_sdf, region.halfspace()).sdf, 64, (-1.0, 1.0))
    assert uncut.bounds[0][0] < -0.95  # the wall fills the box's lower part
    lo, hi = cut.bounds
    c, r = BALL_CENTRE, BALL_RADIUS
    assert np.allclose(hi, c + r, atol=0.04)
    assert np.allclose(lo[:2], (c - r)[:2], atol=0.04)
    assert lo[2] == pytest.approx(WALL_Z + region.margin, abs=0.04)  # flat cap at the margin
    assert len(remove_floaters(cut, 0.0).split(only_watertight=False)) == 1
    assert cut.is_watertight


def test_fit_without_masks_decides_the_region_and_the_model_keeps_it(ball_on_wall, tmp_path):
    import json

    from nepf_core.config import tiny
    from nepf_core.train import fit, load_model

    cfg = tiny()
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every, cfg.train.sync_every = 2, 64, 1, 0
    fit(ball_on_wall, tmp_path / "run", cfg, device="cpu")
    rep = json.loads((tmp_path / "run" / "report.json").read_text())
    dec = {d["decision"]: d for d in rep["decisions"]}
    assert dec["object_region"]["value"] is True and "support plane" in dec["object_region"]["reason"]
    centre, radius = dec["object_frame"]["value"]["centre"], dec["object_frame"]["value"]["radius"]
    hs = rep["run_state"]["object_halfspace"]
    # the wall z = WALL_Z in the object's frame x' = (x - centre) / radius, the margin kept in load units
    assert hs[2] > 0.999
    assert hs[3] == pytest.approx((centre[2] - WALL_Z - RegionConfig().margin) / radius, abs=0.01)
    assert json.loads((tmp_path / "run" / "config.json").read_text())["model"]["object_halfspace"] is None
    model, _, _ = load_model(tmp_path / "run", "cpu")
    assert model.cfg.object_halfspace == pytest.approx(tuple(hs))



def test_enclosing_ball_hand_worked():
    from nepf_core.data.object_region import enclosing_ball
    g = np.random.default_rng(0).normal(size=(4000, 3))
    pts = np.array([2.0, 0.0, 0.0]) + 0.5 * g / np.linalg.norm(g, axis=1, keepdims=True)
    centre, radius = enclosing_ball(pts, np.array([[6.0, 0.0, 0.0]]))
    assert np.allclose(centre, [2.0, 0.0, 0.0], atol=0.02)
    assert radius == pytest.approx(1.1 * 0.5, abs=0.01)            # every point at 0.5, times the margin
    # a camera 0.5 from the centre caps the radius so that it stays outside: 0.5 / 1.05
    _, capped = enclosing_ball(pts, np.array([[6.0, 0.0, 0.0], [2.0, 0.5, 0.0]]))
    assert capped == pytest.approx(0.5 / 1.05, abs=0.01)


def test_an_object_larger_than_the_load_frame_gets_a_frame_that_encloses_it(tmp_path):
    """The load frame's unit sphere is smaller than the ball on the wall (a close-up capture):
    the object frame's ball holds every visible point of it, the points handed to the
    surface prior lie on it, and fit() trains and evaluates in that frame (held-out views
    reframed with the training views)."""
    import json

    from nepf_core.config import tiny
    from nepf_core.data.split import split_scene
    from nepf_core.reframe import object_world_from_norm
    from nepf_core.train import fit
    from nepf_core.train.evaluation import EvalTargets
    from nepf_core.train.hooks import TrainHooks
    from nepf_core.train.rules.masks import decide_object_region as decide_with_frame

    scene = render_ball_on_wall(n_views=16)
    s = 0.3    # load frame = world / s: the ball (radius 0.4 world) is 1.33 load units, beyond the unit sphere
    scene.c2w = scene.c2w.copy()
    scene.c2w[:, :3, 3] /= s
    scene.world_from_norm = np.diag([s, s, s, 1.0])
    hs, decisions, points, frame = decide_with_frame(scene)
    assert frame is not None and [d.name for d in decisions] == ["object_region", "object_frame"]
    centre, radius = frame
    # visible ball surface (in front of the wall), in load units, lies inside the frame's ball
    g = np.random.default_rng(1).normal(size=(2000, 3))
    ball = (BALL_CENTRE + BALL_RADIUS * g / np.linalg.norm(g, axis=1, keepdims=True))
    ball = ball[ball[:, 2] > WALL_Z + 0.05] / s
    assert (np.linalg.norm(ball - centre, axis=1) < radius).all()
    cams = scene.c2w[:, :3, 3]
    assert (np.linalg.norm(cams - centre, axis=1) > radius).all()
    # the prior's points, back in world units, lie on the ball (not on the wall)
    world = (points * radius + centre) * s
    assert len(points) > 50 and np.median(surface_distance(world)) < 0.02
    assert np.median(np.abs(world[:, 2] - WALL_Z)) > 0.1

    train, test = split_scene(scene, 4)
    seen = {}

    class Frames(TrainHooks):
        def after_step(self, run, step, out, losses):
            seen["train"], seen["test"] = run.scene, run.targets.test_scene

    cfg = tiny()
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every, cfg.train.sync_every = 1, 64, 1, 0
    fit(train, tmp_path / "run", cfg, device="cpu", targets=EvalTargets(test_scene=test), hooks=[Frames()])
    expected = object_world_from_norm(scene.world_from_norm, *decide_with_frame(train)[3])
    assert np.allclose(seen["train"].world_from_norm, expected, atol=1e-6)
    assert np.allclose(seen["test"].world_from_norm, expected, atol=1e-6)
    # a held-out camera's centre, mapped back to world units, is where it was
    back = (seen["test"].world_from_norm @ np.r_[seen["test"].c2w[0][:3, 3], 1.0])[:3]
    assert np.allclose(back, (scene.world_from_norm @ np.r_[test.c2w[0][:3, 3], 1.0])[:3], atol=1e-4)
    ck = __import__("torch").load(tmp_path / "run" / "checkpoints" / "latest.pt", weights_only=False)
    assert np.allclose(ck["extra"]["world_from_norm"], expected, atol=1e-6)
    assert [r for r in map(json.loads, (tmp_path / "run" / "metrics.jsonl").read_text().splitlines())
            if r.get("kind") == "test"]
