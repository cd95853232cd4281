"""The material evidence read from the training pixels instead of the radiance network
(``python -m bench.evidence_report RUN SCENE --pixels``): is the network's blur the limit?

The training's evidence (:mod:`nepf_core.render.material_evidence`) reads the radiance network
``R(x*, v_k)`` toward each training camera ``k`` that faces and sees ``x*``. That network smooths
a lobe over directions and over neighbouring points. The pixels themselves are what the camera
saw: project ``x*`` into camera ``k`` (``u = K_k R_k^T (x* - o_k)``, pixel centres at
``i + 0.5``) and sample its linear image bilinearly. Where these colours call metals metal that
the network's colours call dielectric, the network's blur is the limit; where they do not, the
limit is the one-light BSDF fit itself (or the geometry the point is taken from).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor


def camera_of_direction(x: Tensor, v: Tensor, cams: Tensor) -> Tensor:
    """``[P, K]`` long: the camera of ``cams [C, 3]`` whose unit direction from ``x [P, 3]`` is
    ``v [P, K, 3]`` (the closest, by cosine: ``v`` was made from these centres)."""
    to_cam = torch.nn.functional.normalize(cams[None, :, :] - x[:, None, :], dim=-1)   # [P, C, 3]
    return torch.einsum("pkd,pcd->pkc", v, to_cam).argmax(-1)


def sample_pixels(images: Tensor, intrinsics: Tensor, c2w: Tensor, x: Tensor, cam: Tensor) -> tuple[Tensor, Tensor]:
    """``(c [P, K, 3], inside [P, K])``: the bilinear linear colour of camera ``cam [P, K]``'s image
    (``images [N, H, W, 3]``, ``intrinsics [N, 3, 3]``, ``c2w [N, 4, 4]``) at the projection of
    ``x [P, 3]``, and whether that projection falls inside the image in front of the camera."""
    N, H, W, _ = images.shape
    R, o = c2w[cam][..., :3, :3], c2w[cam][..., :3, 3]                                # [P, K, 3, 3], [P, K, 3]
    xc = torch.einsum("pkji,pkj->pki", R, x[:, None, :] - o)                          # R^T (x - o)
    uvw = torch.einsum("pkij,pkj->pki", intrinsics[cam], xc)
    z = uvw[..., 2].clamp_min(1e-8)
    u, v = uvw[..., 0] / z, uvw[..., 1] / z
    inside = (uvw[..., 2] > 0) & (u >= 0) & (u <= W) & (v >= 0) & (v <= H)
    grid = torch.stack([2.0 * u / W - 1.0, 2.0 * v / H - 1.0], -1)                    # align_corners=False
    P, K = cam.shape
    out = torch.empty(P, K, 3, dtype=images.dtype)
    img = images.permute(0, 3, 1, 2)                                                  # [N, 3, H, W]
    for n in cam.unique().tolist():
        sel = cam == n
        g = grid[sel].reshape(1, 1, -1, 2).to(img.dtype)
        out[sel] = torch.nn.functional.grid_sample(img[n:n + 1], g, mode="bilinear",
                                                   align_corners=False)[0, :, 0].T
    return out, inside


def pixels_toward(train, x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """``(c [P, K, 3], inside [P, K])``: :func:`sample_pixels` of the training ``Scene`` ``train``
    (normalised frame) at ``x [P, 3]``, in the camera behind each direction ``v [P, K, 3]``."""
    c2w = torch.as_tensor(np.asarray(train.c2w), dtype=torch.float32)
    cam = camera_of_direction(x, v, c2w[:, :3, 3])
    return sample_pixels(torch.as_tensor(np.asarray(train.images), dtype=torch.float32),
                         torch.as_tensor(np.asarray(train.intrinsics), dtype=torch.float32), c2w, x, cam)


def with_pixel_colours(pts: dict, scene_dir: Path) -> dict:
    """:func:`bench.evidence_report.lit_test_points`'s ``pts`` with ``c`` replaced by the
    training pixels at the same points and cameras (a view whose projection leaves the image is
    no longer valid)."""
    from nepf_core.reframe import load_held_out

    train = load_held_out(scene_dir / "input" / "dtu", pts["world_from_norm"])
    c, inside = pixels_toward(train, torch.as_tensor(pts["x_norm"], dtype=torch.float32), pts["v"])
    return {**pts, "c": c, "valid": pts["valid"] & inside}
