"""The silhouette band and its share of a training batch (train/silhouette_draws.py)."""

import numpy as np
import pytest
import torch

from nepf_core.train.silhouette_draws import SilhouetteDraws, silhouette_band


def test_the_band_is_the_pixels_within_r_of_the_other_side():
    """A 10x10 square in a 20x20 view: a pixel is in the band iff its Chebyshev distance to a
    pixel of the other side is <= r (computed by brute force here)."""
    m = torch.zeros(1, 20, 20)
    m[0, 5:15, 5:15] = 1.0
    band = silhouette_band(m, radius=2)[0].numpy()
    fg = m[0].numpy() > 0.5
    ys, xs = np.mgrid[0:20, 0:20]
    expect = np.zeros((20, 20), bool)
    for y in range(20):
        for x in range(20):
            near = (np.abs(ys - y) <= 2) & (np.abs(xs - x) <= 2)
            expect[y, x] = fg[near].any() and (~fg[near]).any()
    assert np.array_equal(band, expect)
    assert band.sum() == 14 * 14 - 6 * 6   # the 5-pixel ring from 3 to 16


def test_a_batch_takes_its_share_from_the_band_and_the_rest_uniform():
    m = torch.zeros(3, 16, 16)
    m[:, 4:12, 4:12] = 1.0
    draws = SilhouetteDraws(m, 0.25)
    band = silhouette_band(m)
    assert draws.count(1000) == 250
    v, r, c = draws.draw(5000, torch.Generator().manual_seed(0))
    assert band[v, r, c].all()                              # every draw lies in the band
    assert set(v.tolist()) == {0, 1, 2}                     # of every view
    rec = draws.decision().as_record()
    assert rec["value"] == {"band_pixel_fraction": round(float(band.float().mean()), 4), "batch_fraction": 0.25}
    none = SilhouetteDraws(torch.ones(2, 8, 8), 0.25)
    assert none.count(1000) == 0                                   # no silhouette: all uniform
    assert none.decision().value["batch_fraction"] == 0.0 and "uniformly" in none.decision().reason
    with pytest.raises(ValueError, match="silhouette_fraction"):
        SilhouetteDraws(m, 0.0)


def test_the_sampler_draws_the_last_part_of_the_batch_from_the_band():
    from types import SimpleNamespace

    from nepf_core.rays import PixelSampler
    m = np.zeros((2, 16, 16), np.float32)
    m[:, 4:12, 4:12] = 1.0
    K = np.array([[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]])
    scene = SimpleNamespace(n_views=2, height=16, width=16, images=np.random.rand(2, 16, 16, 3).astype(np.float32),
                            masks=m, intrinsics=np.stack([K, K]), c2w=np.stack([np.eye(4)] * 2).astype(np.float32))
    sampler = PixelSampler(scene)
    draws = SilhouetteDraws(torch.from_numpy(m), 0.5)
    rays = sampler.sample(400, torch.Generator().manual_seed(0), band=draws)
    assert len(rays) == 400
    # the mask at the band draws is mixed: about half of them land on the object
    assert 0.3 < float(rays.mask[200:].mean()) < 0.7
    # uniform draws hit the 8x8 square a quarter of the time
    assert 0.15 < float(rays.mask[:200].mean()) < 0.35


def test_a_fit_with_masks_records_the_band_and_draws_from_it(small_scene, tmp_path):
    """A short fit with ``train.silhouette_fraction`` records the band's share of the pixels
    (computed here from the scene's own masks) and the batch's share in ``report.json``."""
    import json

    from nepf_core.config import tiny
    from nepf_core.train import fit
    assert small_scene.masks is not None
    cfg = tiny()
    cfg.train.iters, cfg.train.batch_rays, cfg.train.sync_every = 2, 64, 0
    cfg.train.silhouette_fraction = 0.5
    fit(small_scene, tmp_path / "r", cfg, device="cpu")
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    (dec,) = [d for d in rep["decisions"] if d["decision"] == "silhouette_draws"]
    share = float(silhouette_band(torch.as_tensor(small_scene.masks)).float().mean())
    assert dec["value"] == {"band_pixel_fraction": round(share, 4), "batch_fraction": 0.5}
    assert 0 < share < 0.5


def test_the_importance_weights_are_the_uniform_over_the_mixture_density():
    """Hand-worked: 2 views of 16x16 (P = 512), band B pixels, a batch of R = 8 with k = 2 band
    draws: a band pixel's density is (6/8)/P + (2/8)/B, so q = (1/P) / that; any other 1/(6/8)."""
    m = torch.zeros(2, 16, 16)
    m[:, 4:12, 4:12] = 1.0
    draws = SilhouetteDraws(m, 0.25)
    b = int(silhouette_band(m).sum())
    view, row, col = torch.tensor([0, 1]), torch.tensor([4, 0]), torch.tensor([4, 0])   # on the edge; a corner
    q = draws.importance(view, row, col, 8)
    assert q[0].item() == pytest.approx((1 / 512) / (0.75 / 512 + 0.25 / b))
    assert q[1].item() == pytest.approx(1 / 0.75)


def test_importance_weighted_means_over_mixture_draws_are_the_uniform_mean():
    """The self-normalised weighted mean of a per-pixel value over many mixture batches equals its
    mean over all pixels (the colour terms keep their uniform meaning); the unweighted one does not."""
    from types import SimpleNamespace

    from nepf_core.rays import PixelSampler
    m = np.zeros((2, 16, 16), np.float32)
    m[:, 4:12, 4:12] = 1.0
    img = np.random.default_rng(0).random((2, 16, 16, 3)).astype(np.float32)
    img[:, 2:14, 2:14] += 2.0 * silhouette_band(torch.from_numpy(m)).numpy()[:, 2:14, 2:14, None]   # a bright edge
    K = np.array([[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]])
    scene = SimpleNamespace(n_views=2, height=16, width=16, images=img, masks=m,
                            intrinsics=np.stack([K, K]), c2w=np.stack([np.eye(4)] * 2).astype(np.float32))
    sampler, draws, g = PixelSampler(scene), SilhouetteDraws(torch.from_numpy(m), 0.5), torch.Generator().manual_seed(1)
    num = den = plain = 0.0
    for _ in range(200):
        rays = sampler.sample(512, g, band=draws)
        v = rays.rgb[:, 0]
        num, den, plain = num + float((v * rays.draw_q).sum()), den + float(rays.draw_q.sum()), plain + float(v.mean())
    truth = float(img[..., 0].mean())
    assert num / den == pytest.approx(truth, rel=0.01)
    assert plain / 200 > truth * 1.2          # the band draws alone would overweigh the bright edge


def test_the_colour_terms_weigh_each_ray_by_its_draw_importance():
    """L_r over a batch with draw_q equals sum_r q_r m_r |srgb(L) - srgb(gt)|_1 / (3 sum_r q_r m_r)."""
    from types import SimpleNamespace

    from nepf_core.color import linear_to_srgb
    from nepf_core.losses.batch import loss_batch
    from nepf_core.losses.colour import loss_radiance, loss_surface
    from nepf_core.losses.config import LossConfig
    from nepf_core.rays import RayBatch
    g = torch.Generator().manual_seed(0)
    n = 6
    rays = RayBatch(torch.zeros(n, 3), torch.ones(n, 3), torch.rand(n, 3, generator=g),
                    torch.tensor([1.0, 1, 0, 1, 1, 0]))
    rays.draw_q = torch.tensor([0.3, 1.4, 1.4, 0.3, 1.4, 0.3])
    out = SimpleNamespace(rgb_r=torch.rand(n, 3, generator=g), rgb_vol=torch.rand(n, 3, generator=g),
                          rgb_surf=torch.rand(n, 3, generator=g), w_max=torch.rand(n, generator=g),
                          weight_sum=torch.ones(n))
    b = loss_batch(out, rays, LossConfig(), use_mask=True)
    err = (linear_to_srgb(out.rgb_r) - linear_to_srgb(rays.rgb)).abs().sum(-1)
    w = rays.draw_q * rays.mask
    assert loss_radiance(b).item() == pytest.approx(float((w * err).sum() / (3 * w.sum())), rel=1e-5)
    e_surf = (linear_to_srgb(out.rgb_surf) - linear_to_srgb(out.rgb_r)).abs().mean(-1)
    assert loss_surface(b).item() == pytest.approx(float((w * (1 - out.w_max) * e_surf).sum() / w.sum()), rel=1e-5)
