"""Ray-sphere bounds, stratified samples, inverse-CDF sampling, NeuS up-sampling."""

import math

import torch

from nepf_core.render.sampling import hierarchical_z, near_far_from_sphere, sample_pdf, stratified_z


def test_near_far_hand_worked():
    # ray from (0,0,-3) along +z: enters the unit sphere at t=2, leaves at t=4
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 2.0, -3.0], [0.0, 0.0, 0.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    near, far, hit = near_far_from_sphere(o, d)
    assert torch.allclose(near[0], torch.tensor(2.0)) and torch.allclose(far[0], torch.tensor(4.0))
    assert hit.tolist() == [True, False, True]
    # offset ray misses: NeuS fallback [mid-1, mid+1] = [2, 4]
    assert torch.allclose(near[1], torch.tensor(2.0)) and torch.allclose(far[1], torch.tensor(4.0))
    # starting inside: near clamps to 1e-3, far = 1
    assert abs(float(near[2]) - 1e-3) < 1e-9 and abs(float(far[2]) - 1.0) < 1e-6


def test_stratified_within_bounds_and_sorted():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([3.0, 2.5])
    z = stratified_z(near, far, 16, perturb=True, generator=torch.Generator().manual_seed(0))
    assert (z >= near[:, None]).all() and (z <= far[:, None]).all()
    assert (z[:, 1:] >= z[:, :-1]).all()


def test_sample_pdf_matches_histogram():
    # pdf 3:1 over two bins [0,1], [1,2] -> 75% of samples in the first bin
    bins = torch.tensor([[0.0, 1.0, 2.0]])
    w = torch.tensor([[3.0, 1.0]])
    s = sample_pdf(bins, w, 1000, deterministic=True)
    frac = float((s < 1.0).float().mean())
    assert abs(frac - 0.75) < 0.01
    assert (s >= 0).all() and (s <= 2).all()


def test_hierarchical_samples_concentrate_at_surface():
    # unit-radius 0.5 sphere SDF; rays through the centre hit at t = 3 - 0.5 = 2.5
    sdf = lambda x: x.norm(dim=-1) - 0.5
    o = torch.tensor([[0.0, 0.0, -3.0]]).repeat(4, 1)
    d = torch.tensor([[0.0, 0.0, 1.0]]).repeat(4, 1)
    near, far, _ = near_far_from_sphere(o, d)
    z0 = stratified_z(near, far, 32, perturb=False)
    z = hierarchical_z(o, d, z0, sdf, 32, 4)
    assert z.shape == (4, 64)
    new = z.shape[1] - 32
    close = ((z - 2.5).abs() < 0.1).sum(-1)
    # uniform spacing over [2, 4] puts ~3 of 32 samples within 0.1; importance adds many more
    assert (close >= 20).all(), close
    assert new == 32
