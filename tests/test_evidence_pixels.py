"""bench/evidence_pixels.py: the camera behind each evidence direction, and the projection and
bilinear sampling of a point into a training image, against values worked by hand."""

import math

import pytest
import torch

from bench.evidence_pixels import camera_of_direction, sample_pixels

H, W, F = 4, 6, 5.0


def _ramp_image():
    """``[1, H, W, 3]``: red = column index, green = row index, blue = 1 (so a bilinear sample at
    pixel coordinates ``(u, v)`` reads ``(u - 0.5, v - 0.5, 1)`` inside the centres)."""
    j, i = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    return torch.stack([i, j, torch.ones_like(i)], -1)[None]


def _camera(origin=(0.0, 0.0, 0.0)):
    K = torch.tensor([[[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]]])
    c2w = torch.eye(4)[None].clone()
    c2w[0, :3, 3] = torch.tensor(origin)
    return K, c2w


def _point_at(u, v, z=2.0, origin=(0.0, 0.0, 0.0)):
    """The point in front of the camera at ``origin`` (axes of the world) that projects to ``(u, v)``."""
    return torch.tensor([[(u - W / 2) * z / F + origin[0], (v - H / 2) * z / F + origin[1], z + origin[2]]])


@pytest.mark.parametrize("u, v", [(2.5, 1.5), (3.0, 1.5), (4.25, 2.75)])
def test_a_projected_point_reads_the_bilinear_pixel(u, v):
    K, c2w = _camera(origin=(0.3, -0.2, 0.1))
    x = _point_at(u, v, origin=(0.3, -0.2, 0.1))
    c, inside = sample_pixels(_ramp_image(), K, c2w, x, torch.zeros(1, 1, dtype=torch.long))
    assert bool(inside[0, 0])
    assert c[0, 0].tolist() == pytest.approx([u - 0.5, v - 0.5, 1.0], abs=1e-5)


def test_a_point_behind_or_beside_the_camera_is_not_inside():
    K, c2w = _camera()
    behind = torch.tensor([[0.0, 0.0, -1.0]])
    beside = _point_at(W + 1.0, 1.5)
    for x in (behind, beside):
        _c, inside = sample_pixels(_ramp_image(), K, c2w, x, torch.zeros(1, 1, dtype=torch.long))
        assert not bool(inside[0, 0])


def test_a_rotated_camera_projects_through_its_rotation():
    """A camera turned 90 degrees about y (its z axis along world +x) sees the point on world +x
    at its image centre."""
    K, c2w = _camera()
    c, s = math.cos(math.pi / 2), math.sin(math.pi / 2)
    c2w[0, :3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    col, inside = sample_pixels(_ramp_image(), K, c2w, torch.tensor([[2.0, 0.0, 0.0]]),
                                torch.zeros(1, 1, dtype=torch.long))
    assert bool(inside[0, 0])
    assert col[0, 0, :2].tolist() == pytest.approx([W / 2 - 0.5, H / 2 - 0.5], abs=1e-5)


def test_each_direction_finds_its_camera():
    g = torch.Generator().manual_seed(0)
    cams = torch.randn(7, 3, generator=g) * 3.0
    x = torch.randn(5, 3, generator=g) * 0.3
    pick = torch.randint(0, 7, (5, 4), generator=g)
    v = torch.nn.functional.normalize(cams[pick] - x[:, None, :], dim=-1)
    assert torch.equal(camera_of_direction(x, v, cams), pick)
