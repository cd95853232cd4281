"""OccupancyGrid: never culls the surface, culls empty space, sampler behaviour."""
import math

import pytest
import torch

from nepf_core.fields.grid_encoding import sphere_sdf
from nepf_core.render.occupancy import OccupancyConfig, OccupancyGrid, ray_aabb


def torus_sdf(x, big=0.5, small=0.04):
    q = torch.stack([torch.linalg.vector_norm(x[:, :2], dim=1) - big, x[:, 2]], 1)
    return torch.linalg.vector_norm(q, dim=1) - small


def sphere_pts(n, c, r, g):
    d = torch.randn(n, 3, generator=g)
    return torch.tensor(c) + r * d / d.norm(dim=1, keepdim=True)


def torus_pts(n, g, big=0.5, small=0.04):
    a, b = torch.rand(n, generator=g) * 2 * math.pi, torch.rand(n, generator=g) * 2 * math.pi
    rr = big + small * torch.cos(b)
    return torch.stack([rr * torch.cos(a), rr * torch.sin(a), small * torch.sin(b)], 1)


SHAPES = {
    "sphere": (lambda x: sphere_sdf(x, 0.5), lambda n, g: sphere_pts(n, [0.0, 0.0, 0.0], 0.5, g)),
    "small_offcentre": (
        lambda x: sphere_sdf(x - torch.tensor([0.31, -0.22, 0.13]), 0.12),
        lambda n, g: sphere_pts(n, [0.31, -0.22, 0.13], 0.12, g),
    ),
    "thin_torus": (torus_sdf, torus_pts),
}


@pytest.mark.parametrize("res", [32, 64])
@pytest.mark.parametrize("shape", list(SHAPES))
@pytest.mark.parametrize("lipschitz", [1.0, 1.4])
def test_surface_cells_never_culled(shape, res, lipschitz):
    # lipschitz=1.4 mimics a learned SDF with |grad f| = 1.4 (< safety 1.5): still safe
    sdf, pts = SHAPES[shape]
    grid = OccupancyGrid(OccupancyConfig(resolution=res))
    grid.update(lambda x: lipschitz * sdf(x), inv_s=1e4)
    p = pts(50000, torch.Generator().manual_seed(0))
    assert grid.occupied_at(p).all()
    # and empty space is culled
    assert grid.occupied_fraction() < 0.5


def test_sphere_culls_most_cells_and_band_follows_inv_s():
    grid = OccupancyGrid(OccupancyConfig(resolution=64))
    assert grid.occupied_fraction() == 1.0  # before the first update nothing is culled
    st = grid.update(lambda x: sphere_sdf(x, 0.5), inv_s=200.0)
    assert st["occupied_fraction"] < 0.15
    # small inv_s (early NeuS) keeps a wide band
    st2 = grid.update(lambda x: sphere_sdf(x, 0.5), inv_s=10.0)
    assert st2["occupied_fraction"] > st["occupied_fraction"]
    assert st2["threshold"] == pytest.approx(grid.threshold(10.0))


def test_partial_update_only_adds_occupancy_for_stale_cells():
    grid = OccupancyGrid(OccupancyConfig(resolution=32))
    grid.update(lambda x: sphere_sdf(x, 0.5), inv_s=1e4)
    before = grid.occ.clone()
    grid.update(lambda x: sphere_sdf(x, 0.5), inv_s=1e4, fraction=0.1)
    assert (grid.occ | ~before).all()  # nothing that was occupied got culled
    assert grid.occ.sum() >= before.sum()


@pytest.mark.parametrize("dilation", [0, 1])
def test_update_restricted_to_allowed_cells_queries_only_those(dilation):
    # the visual hull restricts the update: same grid as a full update intersected with the
    # hull, with the SDF evaluated only at the hull's cells
    res = 32
    sdf = lambda x: sphere_sdf(x, 0.5)
    full = OccupancyGrid(OccupancyConfig(resolution=res, dilation=dilation))
    full.update(sdf, inv_s=300.0)
    g = torch.Generator().manual_seed(3)
    allowed = torch.rand(res, res, res, generator=g) < 0.3
    seen = []
    part = OccupancyGrid(OccupancyConfig(resolution=res, dilation=dilation))
    st = part.update(lambda x: (seen.append(x.shape[0]), sdf(x))[1], inv_s=300.0, allowed=allowed)
    assert sum(seen) == st["n_evaluated"] == int(allowed.sum())
    if dilation == 0:
        assert torch.equal(part.occ, full.occ & allowed)
    else:
        assert not (part.occ & ~allowed).any() and (part.occ <= full.occ).all()
        plain = OccupancyGrid(OccupancyConfig(resolution=res))
        plain.update(sdf, inv_s=300.0, allowed=allowed)
        assert (part.occ >= plain.occ).all() and part.occ.sum() > plain.occ.sum()  # dilation still applied


def test_dilation_and_nan_safety():
    grid = OccupancyGrid(OccupancyConfig(resolution=32, dilation=1))
    grid.update(lambda x: sphere_sdf(x, 0.5), inv_s=1e4)
    plain = OccupancyGrid(OccupancyConfig(resolution=32))
    plain.update(lambda x: sphere_sdf(x, 0.5), inv_s=1e4)
    assert (grid.occ | ~plain.occ).all() and grid.occ.sum() > plain.occ.sum()
    plain.update(lambda x: torch.full_like(x[:, 0], float("nan")), inv_s=1e4)
    assert plain.occ.all()


def make_rays(n, gen, miss=False):
    o = torch.randn(n, 3, generator=gen)
    o = o / o.norm(dim=1, keepdim=True) * 2.5
    if miss:
        d = o.clone()  # pointing away from the origin
    else:
        d = torch.randn(n, 3, generator=gen) * 0.25 - o
    d = d / d.norm(dim=1, keepdim=True)
    return o, d, torch.full((n,), 0.5), torch.full((n,), 4.5)


def sphere_hit_t(o, d, r):
    b = (o * d).sum(1)
    c = (o * o).sum(1) - r * r
    disc = b * b - c
    return -b - disc.clamp_min(0).sqrt(), disc > 0


def test_every_ray_that_meets_the_surface_is_a_hit():
    """Rule (1) never culls a segment that holds surface: every ray that meets the sphere crosses
    an occupied march segment."""
    gen = torch.Generator().manual_seed(3)
    grid = OccupancyGrid(OccupancyConfig(resolution=64))
    grid.update(lambda x: sphere_sdf(x, 0.5), inv_s=1e3)
    o, d, near, far = make_rays(512, gen)
    _, hits = sphere_hit_t(o, d, 0.5)
    assert hits.sum() > 100
    assert grid.ray_hits(o, d, near, far)[hits].all()


def test_rays_far_from_the_surface_are_misses():
    gen = torch.Generator().manual_seed(4)
    grid = OccupancyGrid(OccupancyConfig(resolution=32))
    grid.update(lambda x: sphere_sdf(x, 0.5), inv_s=1e3)
    o, d, near, far = make_rays(64, gen, miss=True)
    assert not grid.ray_hits(o, d, near, far).any()


def test_ray_aabb_hand_values():
    o = torch.tensor([[-3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    t_in, t_out = ray_aabb(o, d, 1.0)
    assert torch.allclose(t_in[:2], torch.tensor([2.0, -1.0]))  # enters x=-1 at t=2
    assert torch.allclose(t_out[:2], torch.tensor([4.0, 1.0]))
    assert t_out[2] <= t_in[2]  # y=5 never inside


def test_buffers_follow_device_and_state_dict():
    grid = OccupancyGrid(OccupancyConfig(resolution=16))
    grid.update(lambda x: sphere_sdf(x, 0.5), inv_s=1e3)
    sd = grid.state_dict()
    assert {"sdf_abs", "occ", "n_updates"} <= set(sd)
    g2 = OccupancyGrid(OccupancyConfig(resolution=16))
    g2.load_state_dict(sd)
    assert torch.equal(g2.occ, grid.occ)
    if torch.cuda.is_available():
        gc = grid.to("cuda")
        o, d, near, far = make_rays(8, torch.Generator().manual_seed(0))
        assert gc.ray_hits(o.cuda(), d.cuda(), near.cuda(), far.cuda()).device.type == "cuda"


def test_ray_hits_follow_the_distance_to_an_off_centre_sphere():
    """A ray that passes within the radius of the sphere's centre is a hit; one that passes
    farther than radius + the occupancy band (threshold + half a cell diagonal + half a march
    step, rule (1)) is a miss."""
    c, r = torch.tensor([0.2, 0.0, -0.1]), 0.3
    grid = OccupancyGrid(OccupancyConfig(resolution=32))
    grid.update(lambda x: sphere_sdf(x - c, r), inv_s=1e3)
    g = torch.Generator().manual_seed(5)
    o = 3.0 * torch.nn.functional.normalize(torch.randn(256, 3, generator=g), dim=-1)
    d = torch.nn.functional.normalize(-o + 0.8 * torch.randn(256, 3, generator=g), dim=-1)
    near, far = torch.full((256,), 1.0), torch.full((256,), 5.0)
    hits = grid.ray_hits(o, d, near, far)
    oc = c - o
    dist = (oc - (oc * d).sum(-1, keepdim=True) * d).norm(dim=-1)   # distance of the centre to each ray
    band = grid.threshold(1e3) + math.sqrt(3) / 2 * grid.cell_size + grid.march_step / 2
    assert hits[dist <= r].all() and int((dist <= r).sum()) >= 10
    assert not hits[dist > r + band].any() and int((dist > r + band).sum()) >= 10
