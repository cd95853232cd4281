"""instant-ngp layout (``transforms.json``) and the OpenCV lens-distortion model it uses.

``transforms.json`` (written by instant-ngp's ``colmap2nerf.py``): ``fl_x, fl_y, cx, cy, w, h``
(or ``camera_angle_x``), optional ``k1, k2, p1, p2`` (``k3``), ``aabb_scale``, and
``frames[].transform_matrix``: camera-to-world in the NeRF/OpenGL convention, the same as
Blender's, so it is parsed by :func:`nepf_core.data.blender.parse_transforms`.

What instant-ngp does on top (``nerf_loader.cu``: ``nerf_matrix_to_ngp`` cycles the axes
x,y,z -> y,z,x and applies ``scale`` (default 0.33) and ``offset`` (0.5, 0.5, 0.5) to fit its
unit cube; ``aabb_scale`` widens the cube) is its *internal* frame only. We flip the OpenGL
camera axes to OpenCV and compute our own unit-sphere normalisation (camera rule of
``normalize.py``: instant-ngp captures have no masks), so ``scale``/``offset``/``aabb_scale``
are ignored; ``aabb_scale`` is kept in ``Scene.extras``. ``cx``/``cy`` use pixel centres at
+0.5 (COLMAP's convention), which is ``Scene``'s, so no shift.

Region of interest: instant-ngp's object region is its unit cube, world half side ``0.5 / scale``
(1.5 for the default 0.33) around ``(0.5 - offset) / scale`` (the origin for the default
offset); ``aabb_scale`` only widens the box that holds the *background*. colmap2nerf scales
the cameras so that they frame that cube, so the camera rule of ``normalize.py`` (the ball every
camera sees whole, around the point closest to the optical axes) gives about the same region,
and ``aabb_scale`` is not needed to place it. What lies outside the unit sphere is the
background model's.

Distortion (OpenCV radial-tangential, on normalised coordinates ``x = (u - cx)/fx``):
    ``r^2 = x^2 + y^2``, ``g = 1 + k1 r^2 + k2 r^4 + k3 r^6 (+ k4 r^8, nerfstudio's OPENCV only)``
    ``x_d = x g + 2 p1 x y + p2 (r^2 + 2 x^2)``
    ``y_d = y g + p1 (r^2 + 2 y^2) + 2 p2 x y``
Images are undistorted in the loader, so ``Scene`` stays pinhole with the same ``K``: each
output pixel centre is pushed through the *forward* model and the distorted image is
sampled there bilinearly (the remap needs no inverse); pixels whose source falls outside
the image become black. :func:`undistort_points` (the iterative inverse) is used to
synthesise distorted test images.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from nepf_core.data.assemble import check_whole_set
from nepf_core.data.paths import existing_file
from nepf_core.data.scene import Scene

TRANSFORMS = "transforms.json"


def is_ingp(root: Path) -> bool:
    """True when ``root`` holds ``transforms.json`` (inside ``root``, see ``paths.py``)."""
    return existing_file(root, TRANSFORMS) is not None


def distort_points(xy: np.ndarray, coeffs: tuple) -> np.ndarray:
    """Forward OpenCV model on normalised coordinates: ``[..., 2] -> [..., 2]`` (formula above);
    ``coeffs = (k1, k2, p1, p2[, k3[, k4]])``, missing ones zero."""
    k1, k2, p1, p2, k3, k4 = (tuple(coeffs) + (0.0,) * 6)[:6]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    g = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xd = x * g + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * g + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort_points(xyd: np.ndarray, coeffs: tuple, iters: int = 30) -> np.ndarray:
    """Inverse of :func:`distort_points` by fixed-point iteration (OpenCV's scheme).

    ``x_{k+1} = (x_d - delta(x_k)) / g(x_k)`` with ``delta`` the tangential term; converges
    for the mild distortion of real lenses (|residual| < 1e-10 after 30 steps for |k| < 0.3
    within the image). Shapes ``[..., 2] -> [..., 2]``.
    """
    k1, k2, p1, p2, k3, k4 = (tuple(coeffs) + (0.0,) * 6)[:6]
    xd, yd = xyd[..., 0], xyd[..., 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        g = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x = (xd - dx) / g
        y = (yd - dy) / g
    return np.stack([x, y], axis=-1)


def _pixel_rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """Normalised coordinates of all pixel centres ``(u + 0.5, v + 0.5)``: ``[H, W, 2]``."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pix = np.stack([u, v, np.ones_like(u)], -1)
    xyz = pix @ np.linalg.inv(K).T
    return xyz[..., :2] / xyz[..., 2:3]


def _to_pixels(K: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Normalised ``[..., 2]`` -> array indices ``(row, col)`` ``[2, ...]`` (centres at integers)."""
    p = np.concatenate([xy, np.ones_like(xy[..., :1])], -1) @ K.T
    return np.stack([p[..., 1] - 0.5, p[..., 0] - 0.5])


def _remap(img: np.ndarray, coords: np.ndarray) -> np.ndarray:
    out = np.empty(coords.shape[1:] + img.shape[2:], np.float32)
    for c in range(img.shape[2]):
        out[..., c] = ndimage.map_coordinates(img[..., c], coords, order=1, mode="constant", cval=0.0)
    return out


_MAP_CACHE: dict = {}


def undistort_image(img: np.ndarray, K: np.ndarray, coeffs: tuple) -> np.ndarray:
    """Distorted ``[H, W, C]`` -> pinhole ``[H, W, C]`` with the same ``K`` (Scene convention).

    ``out(u, v) = img(K distort(K^-1 (u + 0.5, v + 0.5)))``, bilinear, black outside.
    The sampling map is cached per ``(K, coeffs, H, W)`` (views usually share intrinsics).
    """
    h, w = img.shape[:2]
    key = (np.asarray(K, np.float64).tobytes(), tuple(coeffs), h, w)
    coords = _MAP_CACHE.get(key)
    if coords is None:
        coords = _to_pixels(K, distort_points(_pixel_rays(K, h, w), coeffs)).astype(np.float32)
        _MAP_CACHE.clear()
        _MAP_CACHE[key] = coords
    return _remap(img, coords)


def distort_image(img: np.ndarray, K: np.ndarray, coeffs: tuple) -> np.ndarray:
    """Pinhole ``[H, W, C]`` -> what a lens with ``coeffs`` records (for synthetic tests).

    ``out(u, v) = img(K undistort(K^-1 (u + 0.5, v + 0.5)))``, bilinear, black outside.
    """
    h, w = img.shape[:2]
    coords = _to_pixels(K, undistort_points(_pixel_rays(K, h, w), coeffs))
    return _remap(img, coords)


def load_ingp(root: Path | str, split: str = "train", *, downscale: int = 1,
              max_views: int | None = None, max_side: int | None = None,
              max_total_pixels: int | None = None) -> Scene:
    """Load an instant-ngp ``transforms.json`` folder as a :class:`Scene` (all frames).

    instant-ngp folders have no splits: ``split`` must be ``"train"`` or ``"all"``.
    ``max_side`` (working resolution) and ``max_total_pixels`` (decoded-pixel budget): see
    :func:`nepf_core.data.blender.load_transforms`.
    """
    from nepf_core.data.blender import load_transforms, read_json

    root = Path(root)
    check_whole_set(split, "instant-ngp", "all frames", TRANSFORMS)
    path = root / TRANSFORMS
    scene = load_transforms(root, path, fmt="ingp", split=split, downscale=downscale,
                            max_views=max_views, max_side=max_side, max_total_pixels=max_total_pixels)
    meta = read_json(path, root)
    if "aabb_scale" in meta:
        scene.extras["aabb_scale"] = meta["aabb_scale"]
    return scene
