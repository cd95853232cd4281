"""The training images' colour of a 3D point (``render/view_pixels.py``): projection round trips
with the rays of ``nepf_core.rays``, bilinear values worked by hand, and the validity rules."""

from __future__ import annotations

import math

import numpy as np
import torch

from nepf_core.data.scene import Scene
from nepf_core.rays import PixelSampler, rays_from_pixels
from nepf_core.render.view_pixels import TrainingViews


def _look_at(eye, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) looking from ``eye`` at ``target``."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], 1)
    m[:3, 3] = eye
    return m


def _scene(H=12, W=16, masks=False) -> Scene:
    rng = np.random.default_rng(0)
    eyes = [(3.0, 0.0, 0.5), (0.0, -3.0, 1.0), (-2.0, 2.0, -0.5)]
    c2w = np.stack([_look_at(e) for e in eyes]).astype(np.float32)
    K = np.array([[20.0, 0, W / 2 + 0.3], [0, 22.0, H / 2 - 0.4], [0, 0, 1]], np.float32)
    images = rng.random((3, H, W, 3)).astype(np.float32)
    m = None
    if masks:
        m = np.ones((3, H, W), bool)
        m[:, :, : W // 2] = False
    return Scene(images=images, masks=m, intrinsics=np.stack([K] * 3), c2w=c2w, world_from_norm=np.eye(4),
                 names=["a", "b", "c"])


def test_a_point_on_a_pixels_ray_projects_back_to_that_pixel_with_its_colour():
    scene = _scene()
    sampler = PixelSampler(scene)
    views = TrainingViews.of_sampler(sampler)
    cols = torch.tensor([0.0, 7.0, 15.0, 3.0])
    rows = torch.tensor([0.0, 5.0, 11.0, 8.0])
    for k in range(3):
        view = torch.full((4,), k)
        o, d = rays_from_pixels(sampler.K_inv[view], sampler.c2w[view], cols + 0.5, rows + 0.5)
        x = o + 2.5 * d
        col, row, depth = views.project(x, view[:, None])
        assert torch.allclose(col[:, 0], cols, atol=1e-4) and torch.allclose(row[:, 0], rows, atol=1e-4)
        assert torch.all(depth > 0)
        c, seen = views.colours(x, view[:, None])
        want = sampler.images[k, rows.long(), cols.long()].float()
        assert seen.all() and torch.allclose(c[:, 0], want, atol=1e-3)


def test_between_pixel_centres_the_colour_is_the_bilinear_mix_of_the_four():
    scene = _scene()
    sampler = PixelSampler(scene)
    views = TrainingViews.of_sampler(sampler)
    col, row = 6.25, 3.75                              # between pixels (6, 3), (7, 3), (6, 4), (7, 4)
    view = torch.tensor([1])
    o, d = rays_from_pixels(sampler.K_inv[view], sampler.c2w[view], torch.tensor([col + 0.5]),
                            torch.tensor([row + 0.5]))
    c, seen = views.colours(o + 3.0 * d, view[:, None])
    img = sampler.images[1].float()
    want = (0.75 * 0.25 * img[3, 6] + 0.25 * 0.25 * img[3, 7] + 0.75 * 0.75 * img[4, 6] + 0.25 * 0.75 * img[4, 7])
    assert seen.all() and torch.allclose(c[0, 0], want, atol=1e-3)


def test_points_behind_off_the_image_or_on_background_pixels_do_not_count():
    scene = _scene(masks=True)
    sampler = PixelSampler(scene)
    views = TrainingViews.of_sampler(sampler)
    eye = torch.from_numpy(scene.c2w[0, :3, 3])
    fwd = torch.from_numpy(scene.c2w[0, :3, 2])
    right = torch.from_numpy(scene.c2w[0, :3, 0])
    behind = eye - 2.0 * fwd                           # depth < 0
    far_off = eye + 1.0 * fwd + 5.0 * right            # column far past the image's right edge
    on_left = eye + 3.0 * fwd - 0.2 * right            # left half: masked background
    on_right = eye + 3.0 * fwd + 0.2 * right           # right half: foreground
    x = torch.stack([behind, far_off, on_left, on_right]).float()
    _, seen = views.colours(x, torch.zeros(4, 1, dtype=torch.long))
    assert seen[:, 0].tolist() == [False, False, False, True]


def test_the_metal_evidence_reads_the_images_when_given_them():
    """``views_of_points`` with ``pixels`` returns the images' colours, not the radiance network's."""
    from nepf_core.config import preset
    from nepf_core.model import NePFModel
    from nepf_core.render.material_evidence import views_of_points

    scene = _scene()
    sampler = PixelSampler(scene)
    views = TrainingViews.of_sampler(sampler)
    model = NePFModel(preset("tiny").model)
    x = torch.tensor([[0.0, 0.0, 0.0]])                # the orbit's centre: every camera faces it
    n = torch.tensor([[1.0, 0.0, 0.0]])
    cams = sampler.c2w[:, :3, 3]
    with torch.no_grad():
        c, v, valid = views_of_points(model, x, n, cams, 3, torch.Generator().manual_seed(0), pixels=views)
    # the camera each draw took is the one its direction points at
    cam = torch.stack([(cams - x[0]).div((cams - x[0]).norm(dim=-1, keepdim=True)) @ v[0, j] for j in range(3)]).argmax(-1)
    want, seen = views.colours(x, cam[None, :])
    assert torch.allclose(c, want.float()) and torch.equal(valid & seen, valid)
    assert math.isclose(float(v.norm(dim=-1).mean()), 1.0, rel_tol=1e-5)


def test_the_blur_keeps_a_flat_foreground_flat_and_never_reads_the_background():
    """Normalised convolution: a constant colour inside the mask stays that colour up to the mask's
    edge (the background, here bright red, never bleeds in), and a single bright pixel spreads
    into a Gaussian of the given sigma (its centre keeps 1 / (2 pi sigma^2) of it)."""
    from nepf_core.render.view_pixels import blur_within_masks

    H, W, sigma = 21, 21, 1.5
    img = torch.zeros(1, H, W, 3)
    img[..., 0] = 1.0                                     # red background
    mask = torch.zeros(1, H, W, dtype=torch.bool)
    mask[:, :, 10:] = True
    img[0, :, 10:] = torch.tensor([0.2, 0.4, 0.6])
    out = blur_within_masks(img, mask, sigma)
    assert torch.allclose(out[0, :, 10:], torch.tensor([0.2, 0.4, 0.6]).expand(H, W - 10, 3), atol=1e-5)

    dot = torch.zeros(1, H, W, 3)
    dot[0, 10, 10] = 1.0
    out = blur_within_masks(dot, None, sigma)
    g = torch.exp(-0.5 * (torch.arange(-5, 6.0) / sigma) ** 2)
    g = g / g.sum()
    assert math.isclose(float(out[0, 10, 10, 0]), float(g[5] ** 2), rel_tol=1e-4)
    assert math.isclose(float(out[0, 10, 12, 0]), float(g[5] * g[7]), rel_tol=1e-4)
    assert math.isclose(float(out[0].sum()), 3.0, rel_tol=1e-4)
