"""Metrics by value: PSNR, SSIM (full frame and foreground), aligned albedo PSNR, the sRGB
OETF, and the point-to-mesh Chamfer distance with its floor."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from nepf_core.color import linear_to_srgb
from nepf_core.evaluate import SSIM_BORDER, albedo_psnr_aligned, psnr, ssim
from nepf_core.meshing import chamfer_distance, point_mesh_distance

C1, C2 = 0.01 ** 2, 0.03 ** 2  # SSIM constants for data range 1 (Wang et al. 2004)


def srgb_reference(x: float) -> float:
    """IEC 61966-2-1 sRGB OETF."""
    x = min(max(x, 0.0), 1.0)
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


# ---------------------------------------------------------------- sRGB
@pytest.mark.parametrize("x, want", [(0.0, 0.0), (1.0, 1.0), (0.0031308, 0.04044994),
                                     (0.5, 0.73535698), (0.21404114, 0.5), (0.001, 0.01292),
                                     (-0.5, 0.0), (2.0, 1.0)])
def test_srgb_encode_hand_values(x, want):
    assert float(linear_to_srgb(torch.tensor(x, dtype=torch.float64))) == pytest.approx(want, abs=1e-7)
    assert float(linear_to_srgb(np.array(x))) == pytest.approx(want, abs=1e-7)


def test_srgb_encode_matches_the_standard_on_a_sweep():
    xs = np.linspace(-0.1, 1.1, 1201)
    want = np.array([srgb_reference(float(x)) for x in xs])
    assert np.allclose(linear_to_srgb(torch.from_numpy(xs)).numpy(), want, atol=1e-12)
    assert np.allclose(linear_to_srgb(xs), want, atol=1e-12)


# ---------------------------------------------------------------- PSNR
def test_psnr_hand_values():
    gt = np.zeros((4, 4, 3))
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0)  # MSE 0.01
    mask = np.zeros((4, 4), bool)
    mask[0, 0] = True
    pred = gt.copy()
    pred[0, 0] = 0.01  # MSE 1e-4 on the one masked pixel
    pred[1:, :] = 1.0  # ignored
    assert psnr(pred, gt, mask) == pytest.approx(40.0)
    assert math.isnan(psnr(pred, gt, np.zeros((4, 4), bool)))


# ---------------------------------------------------------------- SSIM
def _const_pair(h=40, w=40):
    """Left half: pred 0.5 against gt 0.25 (constant), right half: both 0.7."""
    pred = np.full((h, w, 3), 0.7)
    gt = np.full((h, w, 3), 0.7)
    pred[:, : w // 2] = 0.5
    gt[:, : w // 2] = 0.25
    return pred, gt


def test_ssim_of_constant_images_is_the_luminance_term():
    """No variance: ``S = (2 a b + C1) / (a^2 + b^2 + C1)`` (the contrast term is C2 / C2)."""
    a, b = 0.5, 0.25
    want = (2 * a * b + C1) / (a * a + b * b + C1)  # 0.800064...
    pred, gt = np.full((32, 32, 3), a), np.full((32, 32, 3), b)
    assert ssim(pred, gt) == pytest.approx(want, abs=1e-9)
    assert ssim(pred, gt, np.ones((32, 32), bool)) == pytest.approx(want, abs=1e-9)
    assert ssim(gt, gt) == pytest.approx(1.0)


def test_masked_ssim_is_the_map_mean_over_the_mask():
    pred, gt = _const_pair()
    a, b = 0.5, 0.25
    want = (2 * a * b + C1) / (a * a + b * b + C1)
    mask = np.zeros((40, 40), bool)
    mask[:, : 20 - SSIM_BORDER - 1] = True  # the windows of these pixels stay inside the left half
    assert ssim(pred, gt, mask) == pytest.approx(want, abs=1e-9)
    mask_right = np.zeros((40, 40), bool)
    mask_right[:, 20 + SSIM_BORDER + 1:] = True
    assert ssim(pred, gt, mask_right) == pytest.approx(1.0, abs=1e-9)
    # the full frame mixes both halves: between the two
    assert want < ssim(pred, gt) < 1.0


def test_masked_ssim_is_not_inflated_by_shared_background():
    """A foreground error on a black frame: the old protocol (both images multiplied by the
    mask, full-frame mean) scored the matching black background as perfect."""
    rng = np.random.default_rng(0)
    gt = np.zeros((64, 64, 3))
    mask = np.zeros((64, 64), bool)
    mask[20:44, 20:44] = True
    gt[mask] = rng.uniform(0.2, 0.8, (mask.sum(), 3))
    pred = gt.copy()
    pred[mask] = np.clip(gt[mask] + rng.normal(0, 0.1, (mask.sum(), 3)), 0, 1)
    fg_only = ssim(pred, gt, mask)
    old = ssim(pred * mask[..., None], gt * mask[..., None])
    assert old > fg_only + 0.05  # measured 0.97 against 0.89
    assert math.isnan(ssim(pred, gt, np.zeros((64, 64), bool)))


def test_ssim_map_matches_an_independent_implementation():
    """The masked mean against SSIM written out with scipy's Gaussian filter."""
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(1)
    gt = rng.uniform(0, 1, (30, 36, 3))
    pred = np.clip(gt + rng.normal(0, 0.15, gt.shape), 0, 1)

    def blur(x):
        return np.stack([gaussian_filter(x[..., c], 1.5, truncate=3.5, mode="reflect") for c in range(3)], -1)
    mx, my = blur(pred), blur(gt)
    sxx, syy, sxy = blur(pred * pred) - mx * mx, blur(gt * gt) - my * my, blur(pred * gt) - mx * my
    smap = (2 * mx * my + C1) * (2 * sxy + C2) / ((mx * mx + my * my + C1) * (sxx + syy + C2))
    mask = rng.uniform(size=(30, 36)) < 0.4
    inner = np.zeros_like(mask)
    inner[SSIM_BORDER:-SSIM_BORDER, SSIM_BORDER:-SSIM_BORDER] = True
    assert ssim(pred, gt, mask) == pytest.approx(float(smap[mask & inner].mean()), abs=1e-9)
    assert ssim(pred, gt) == pytest.approx(float(smap[inner].mean()), abs=1e-9)


# ---------------------------------------------------------------- aligned albedo PSNR
def test_albedo_psnr_aligned_recovers_a_per_channel_scale():
    rng = np.random.default_rng(2)
    gt = rng.uniform(0.1, 0.4, (2, 5, 6, 3))
    mask = np.ones((2, 5, 6), bool)
    mask[0, 0, 0] = False
    pred = gt / np.array([2.0, 0.5, 1.0])
    pred[0, 0, 0] = 0.9  # outside the mask: must not change the scale
    p, scale = albedo_psnr_aligned(pred, gt, mask)
    assert np.allclose(scale, [2.0, 0.5, 1.0])
    assert p == pytest.approx(100.0)  # exact match: MSE floored at 1e-10


def test_albedo_psnr_aligned_hand_worked():
    """One channel pair per pixel, two pixels: p = (0.1, 0.2), g = (0.1, 0.1) in every channel:
    ``s = (0.01 + 0.02) / (0.01 + 0.04) = 0.6``, aligned (0.06, 0.12), PSNR on sRGB values."""
    pred = np.array([0.1, 0.2])[None, :, None, None] * np.ones((1, 2, 1, 3))
    gt = np.full((1, 2, 1, 3), 0.1)
    mask = np.ones((1, 2, 1), bool)
    p, scale = albedo_psnr_aligned(pred, gt, mask)
    assert np.allclose(scale, 0.6)
    err = [(srgb_reference(0.06) - srgb_reference(0.1)) ** 2, (srgb_reference(0.12) - srgb_reference(0.1)) ** 2]
    assert p == pytest.approx(-10 * math.log10(sum(err) / 2), abs=1e-9)


# ---------------------------------------------------------------- Chamfer
def _square(x0, x1, y0, y1, z) -> trimesh.Trimesh:
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    return trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False)


def test_chamfer_parallel_squares_is_the_gap():
    assert chamfer_distance(_square(0, 1, 0, 1, 0), _square(0, 1, 0, 1, 0.1), n_samples=2000) == \
        pytest.approx(0.1, abs=1e-12)


def test_chamfer_half_overlapping_squares():
    """A = [0,1]^2, B = [0,2]x[0,1] (same plane): A -> B is 0; half of B lies over A (0), the
    other half at ``x - 1`` ~ U(0, 1) (mean 0.5): ``CD = (0 + 0.25) / 2 = 0.125``, up to the
    Monte-Carlo error of B's mean (std 0.32 / sqrt(n) = 1e-3 at n = 1e5)."""
    cd = chamfer_distance(_square(0, 1, 0, 1, 0), _square(0, 2, 0, 1, 0), n_samples=100_000)
    assert cd == pytest.approx(0.125, abs=5e-3)


def _torus_mesh(res: int = 64) -> trimesh.Trimesh:
    """The synthetic torus GT mesh recipe (marching cubes of the exact SDF), unit-sphere units."""
    from skimage.measure import marching_cubes

    from nepf_core.data.synth_shapes import sdf_torus
    ax = np.linspace(-1.1, 1.1, res)
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1)
    f = sdf_torus(torch.from_numpy(g.reshape(-1, 3))).numpy().reshape(res, res, res)
    v, faces, _, _ = marching_cubes(f, 0.0, spacing=(ax[1] - ax[0],) * 3)
    return trimesh.Trimesh((v - 1.1) / 1.1, faces[:, ::-1], process=False)


def test_chamfer_floor_and_offset_on_a_torus():
    """GT against GT is the protocol's floor: ~1e-8, far below the values compared (~5e-3), where
    point-to-point distances between two 100k sample sets give ~4e-3. A copy moved 0.005 along
    its normals reads 0.005."""
    mesh = _torus_mesh()
    floor = chamfer_distance(mesh, mesh, n_samples=10_000)
    assert floor < 1e-6
    moved = trimesh.Trimesh(mesh.vertices + 0.005 * mesh.vertex_normals, mesh.faces, process=False)
    assert chamfer_distance(mesh, moved, n_samples=10_000) == pytest.approx(0.005, rel=0.02)


def test_point_mesh_distance_against_brute_force():
    """Exact where certified; far points (cap k_max reached) stay within R of the exact value."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.normal(size=(150, 3)) * 0.7, rng.normal(size=(50, 3)) * 4.0])
    tri = mesh.triangles
    brute = np.array([np.linalg.norm(trimesh.triangles.closest_point(tri, np.repeat(p[None], len(tri), 0)) - p,
                                     axis=-1).min() for p in pts])
    exact = point_mesh_distance(pts, mesh, k_max=len(tri))
    assert np.allclose(exact, brute, atol=1e-12)
    capped = point_mesh_distance(pts, mesh, k_start=2, k_max=4)
    reach = np.linalg.norm(tri - tri.mean(1)[:, None], axis=-1).max()
    assert np.all(capped >= brute - 1e-12) and np.all(capped <= brute + reach)
    near = np.abs(np.linalg.norm(pts, axis=-1) - 1.0) < 0.05
    assert near.any() and np.allclose(point_mesh_distance(pts[near], mesh), brute[near], atol=1e-12)


def test_point_mesh_distance_rejects_an_empty_mesh():
    with pytest.raises(ValueError, match="no faces"):
        point_mesh_distance(np.zeros((2, 3)), trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)))
