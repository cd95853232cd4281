"""A sparse point cloud of what the cameras see, triangulated from image features and the known poses.

Used to find where the object is in a capture without masks (:mod:`nepf_core.data.object_region`)
*before* training: the fitted SDF cannot say it, because early on (and on a CPU budget, all run)
it is a fog that fills the region of interest.

Per view: ORB keypoints and binary descriptors (scikit-image) on the grey image. Each view is
matched with its ``neighbours`` nearest cameras (mutual nearest neighbours, Lowe ratio
``max_ratio``). The poses are known, so a match must satisfy the epipolar constraint

    F = K_j^-T [t]_x R K_i^-1,   (R, t) = pose of camera i in camera j's frame
    Sampson distance  (x_j^T F x_i)^2 / ((F x_i)_1^2 + (F x_i)_2^2 + (F^T x_j)_1^2 + (F^T x_j)_2^2) < max_epipolar_px^2

and is triangulated by the midpoint of the two rays' closest points (both in front of their
camera, the rays at least ``min_angle_deg`` apart, so depth is defined). Shapes: ``Scene`` views
``[N, H, W, 3]``; returns ``[P, 3]`` points in the scene's (normalised) frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SparseConfig:
    """How features are found, matched and triangulated."""

    n_keypoints: int = 1000
    """ORB keypoints per view."""
    neighbours: int = 3
    """Each view is matched with this many nearest cameras."""
    max_ratio: float = 0.85
    """Lowe ratio test of the descriptor matches."""
    max_epipolar_px: float = 1.0
    """Largest Sampson distance (pixels) of a match to its epipolar line."""
    min_angle_deg: float = 1.5
    """Smallest angle between the two rays of a triangulated point."""


def _grey(image: np.ndarray) -> np.ndarray:
    """Linear RGB ``[H, W, 3]`` -> perceptual grey ``[H, W]`` (features are found on sRGB-like values)."""
    return (np.clip(image, 0.0, 1.0) ** (1.0 / 2.2)) @ np.array([0.2126, 0.7152, 0.0722])


def fundamental(K_i: np.ndarray, c2w_i: np.ndarray, K_j: np.ndarray, c2w_j: np.ndarray) -> np.ndarray:
    """``F`` with ``x_j^T F x_i = 0`` for pixel coordinates (module docstring): ``[3, 3]``."""
    rel = np.linalg.inv(c2w_j) @ c2w_i
    R, t = rel[:3, :3], rel[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.linalg.inv(K_j).T @ tx @ R @ np.linalg.inv(K_i)


def sampson_distance(F: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """First-order distance (pixels) of the pairs ``x_i, x_j [M, 2]`` from ``x_j^T F x_i = 0``: ``[M]``."""
    a, b = np.c_[x_i, np.ones(len(x_i))], np.c_[x_j, np.ones(len(x_j))]
    Fa, Fb = a @ F.T, b @ F
    num = (b * Fa).sum(1) ** 2
    den = Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Fb[:, 0] ** 2 + Fb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))


def pixel_rays(K: np.ndarray, c2w: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Unit world directions through pixel coordinates ``uv [M, 2]`` (OpenCV camera): ``[M, 3]``."""
    d = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T @ c2w[:3, :3].T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def midpoint_triangulation(o_a: np.ndarray, d_a: np.ndarray, o_b: np.ndarray, d_b: np.ndarray,
                           min_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint of the closest points of rays ``o_a + s d_a`` and ``o_b + t d_b`` (``d [M, 3]`` unit):
    ``(points [M, 3], valid [M])``, valid where ``s, t > 0`` and the rays are ``min_angle_deg`` apart."""
    w = o_a - o_b
    b = (d_a * d_b).sum(1)
    dw_a, dw_b = (d_a * w).sum(1), (d_b * w).sum(1)
    den = np.maximum(1.0 - b * b, 1e-12)
    s = (b * dw_b - dw_a) / den
    t = (dw_b - b * dw_a) / den
    pts = 0.5 * ((o_a + s[:, None] * d_a) + (o_b + t[:, None] * d_b))
    valid = (s > 0) & (t > 0) & (b < np.cos(np.radians(min_angle_deg)))
    return pts, valid


def triangulate_scene(scene, cfg: SparseConfig | None = None) -> np.ndarray:
    """Sparse points ``[P, 3]`` (the scene's frame) from ORB matches between neighbouring views."""
    from skimage.feature import ORB, match_descriptors

    cfg = cfg or SparseConfig()
    K = np.asarray(scene.intrinsics, np.float64)
    c2w = np.asarray(scene.c2w, np.float64)
    centres = c2w[:, :3, 3]
    feats = []
    for image in scene.images:
        orb = ORB(n_keypoints=cfg.n_keypoints, fast_threshold=0.05)
        try:
            orb.detect_and_extract(_grey(np.asarray(image, np.float64)))
            feats.append((orb.keypoints[:, ::-1] + 0.5, orb.descriptors))  # (row, col) -> pixel centres (u, v)
        except (RuntimeError, ValueError):  # a flat or tiny image: no keypoints
            feats.append((np.zeros((0, 2)), np.zeros((0, 256), bool)))
    pairs = set()
    for i in range(len(centres)):
        for j in np.argsort(np.linalg.norm(centres - centres[i], axis=1))[1:cfg.neighbours + 1]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    points = []
    for i, j in sorted(pairs):
        if len(feats[i][0]) == 0 or len(feats[j][0]) == 0:
            continue
        m = match_descriptors(feats[i][1], feats[j][1], cross_check=True, max_ratio=cfg.max_ratio)
        if len(m) == 0:
            continue
        a, b = feats[i][0][m[:, 0]], feats[j][0][m[:, 1]]
        keep = sampson_distance(fundamental(K[i], c2w[i], K[j], c2w[j]), a, b) < cfg.max_epipolar_px
        a, b = a[keep], b[keep]
        pts, valid = midpoint_triangulation(np.broadcast_to(centres[i], (len(a), 3)), pixel_rays(K[i], c2w[i], a),
                                            np.broadcast_to(centres[j], (len(b), 3)), pixel_rays(K[j], c2w[j], b),
                                            cfg.min_angle_deg)
        points.append(pts[valid])
    return np.concatenate(points) if points else np.zeros((0, 3))


#: Fewer structure-from-motion points than this are not trusted to place the object region.
MIN_CAPTURE_POINTS = 100


def scene_points(scene, cfg: SparseConfig | None = None) -> tuple[np.ndarray, str]:
    """``(points [P, 3] in the scene's frame, source)``: the capture's own sparse points where it has
    them (``Scene.points``: COLMAP ``points3D``, nerfstudio ``ply_file_path``; at least
    :data:`MIN_CAPTURE_POINTS`), else ORB points triangulated from the images (:func:`triangulate_scene`).

    Why prefer them: they come from matching and bundle adjustment over every image, not from a few
    neighbour pairs with the poses held fixed, and they cost no feature extraction here."""
    pts = getattr(scene, "points", None)
    if pts is not None and len(pts) >= MIN_CAPTURE_POINTS:
        return np.asarray(pts, dtype=np.float64), f"the capture's {scene.source_format} sparse points"
    return triangulate_scene(scene, cfg), "points triangulated from the images"
