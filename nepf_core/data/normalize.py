"""Camera checks and the unit-sphere normalisation for formats that do not carry one.

DTU/IDR/NeuS data come with ``scale_mat`` (normalised -> world). Blender and instant-ngp
transforms do not, so we estimate a similarity ``world_from_norm = [[r I, c], [0, 1]]``
(no rotation) with this rule:

1. **Centre guess** ``c0``: the least-squares point closest to all optical axes,
   ``c0 = argmin_p sum_i |(I - d_i d_i^T)(p - o_i)|^2`` (o_i camera centre, d_i unit
   viewing direction). Falls back to the world origin when the axes are (nearly) parallel
   (smallest eigenvalue of ``sum_i (I - d_i d_i^T) / N`` below 1e-3) or fewer than 2 views:
   Blender and instant-ngp (colmap2nerf) put the object at the origin by convention.
2. **With masks and >= 3 views**: a coarse visual hull. Voxels of a 64^3 grid on a cube
   around ``c0`` (half side 0.95 * the nearest camera distance) are kept when they project
   inside the mask in every view whose image they fall in, and fall in at least half of the
   images. A second 64^3 pass over the first hull's bounding box refines it. Then
   ``c`` = centre of the hull's bounding box, ``r = margin * (max_v |v - c| + voxel half
   diagonal)``.
3. **Otherwise** (no masks, too few views, or an empty hull): ``c = c0`` and
   ``r = margin * min_i d_i * sin(phi_i)``, with ``d_i = |o_i - c|`` and ``phi_i`` the half
   field of view of view ``i`` along its narrower image axis: the largest ball around ``c``
   that every camera sees whole. An object framed by all cameras lies inside it.

``margin`` defaults to 1.1. Finally the radius is capped at ``min_i |o_i - c| / 1.05`` so
every camera stays outside the unit sphere (NeuS-style near/far bounds need it); with
few, close, wide-angle views the visual hull is loose and this cap is what binds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nepf_core.data.errors import DatasetError

#: Cameras end up at least this far from the normalised origin.
CAMERA_CLEARANCE = 1.05
#: OpenGL (x right, y up, z backward) <-> OpenCV (x right, y down, z forward) camera axes.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_to_opencv(c2w_gl: np.ndarray) -> np.ndarray:
    """``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)`` (flip the camera's y and z axes); ``[..., 4, 4]``."""
    return np.asarray(c2w_gl, dtype=np.float64) @ GL_TO_CV


def as_4x4(m: np.ndarray, what: str, *, label: str | None, view: int | None) -> np.ndarray:
    """A ``[3, 4]`` or ``[4, 4]`` matrix as float64 ``[4, 4]`` (``[0, 0, 0, 1]`` appended);
    ``invalid_camera`` for any other shape, ``nonfinite_camera`` for NaN/inf (``what`` names it)."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4):
        raise DatasetError(f"{what} has shape {m.shape}, expected 4x4 or 3x4", file=label, view=view,
                           code="invalid_camera")
    if not np.isfinite(m).all():
        raise DatasetError(f"{what} has NaN or infinite entries", file=label, view=view,
                           code="nonfinite_camera")
    return m


def check_c2w(c2w: np.ndarray, *, label: str | None, view: int | None) -> np.ndarray:
    """Validate a camera-to-world matrix and return it as ``[4, 4]`` float64.

    Accepts ``[3, 4]`` or ``[4, 4]`` (:func:`as_4x4`). Raises ``singular_camera`` when
    ``|det R| < 1e-6`` and ``invalid_camera`` when the rotation block is not orthonormal
    (``max |R^T R - I| > 1e-2``) or is a reflection.
    """
    m = as_4x4(c2w, "camera matrix", label=label, view=view)
    R = m[:3, :3]
    det = np.linalg.det(R)
    if abs(det) < 1e-6:
        raise DatasetError("camera rotation is singular (det = %.3g)" % det, file=label, view=view,
                           code="singular_camera")
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-2 or det < 0:
        raise DatasetError("camera rotation is not a proper rotation (not orthonormal or a reflection)",
                           file=label, view=view, code="invalid_camera")
    return m


def check_intrinsics(K: np.ndarray, *, label: str | None, view: int | None) -> np.ndarray:
    """Validate a pinhole ``K`` (finite, ``fx, fy > 0``, ``K[2] = (0, 0, 1)``); returns float64 ``[3, 3]``."""
    K = np.asarray(K, dtype=np.float64)
    if not np.isfinite(K).all():
        raise DatasetError("intrinsics have NaN or infinite entries", file=label, view=view,
                           code="nonfinite_camera")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(np.linalg.det(K)) < 1e-12:
        raise DatasetError(f"focal lengths must be positive (fx={K[0, 0]:.4g}, fy={K[1, 1]:.4g})",
                           file=label, view=view, code="singular_camera")
    return K


@dataclass
class Normalization:
    """A similarity without rotation: ``x_world = radius * x_norm + centre``.

    Attributes:
        centre: ``[3]`` world position of the normalised origin.
        radius: world length of one normalised unit.
        method: which rule produced it (``"visual_hull"``, ``"frustum"``, ``"given"``).
    """

    centre: np.ndarray
    radius: float
    method: str = "given"

    @property
    def world_from_norm(self) -> np.ndarray:
        """``[4, 4]`` float64 ``[[r I, c], [0, 1]]``."""
        m = np.eye(4)
        m[:3, :3] *= self.radius
        m[:3, 3] = self.centre
        return m


def c2w_to_normalized(c2w_world: np.ndarray, world_from_norm: np.ndarray) -> np.ndarray:
    """Map camera poses into the normalised frame, keeping rotations orthonormal.

    For a similarity ``world_from_norm = [[s Q, c], [0, 1]]``:
    ``c2w_norm = [[Q^T R, Q^T (o - c) / s], [0, 1]]``. Shapes ``[N, 4, 4] -> [N, 4, 4]``.
    """
    A = np.asarray(world_from_norm, np.float64)
    s = np.cbrt(np.linalg.det(A[:3, :3]))
    Q = A[:3, :3] / s
    out = np.array(c2w_world, dtype=np.float64, copy=True)
    out[:, :3, :3] = Q.T @ out[:, :3, :3]
    out[:, :3, 3] = ((out[:, :3, 3] - A[:3, 3]) @ Q) / s
    return out


def nearest_point_to_axes(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, bool]:
    """Least-squares point closest to the lines ``o_i + t d_i``; ``[N, 3], [N, 3] -> [3], ok``.

    Solves ``(sum_i P_i) p = sum_i P_i o_i`` with ``P_i = I - d_i d_i^T``. ``ok`` is False
    (and the origin is returned) for fewer than 2 lines or nearly parallel lines.
    """
    d = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = P.sum(0)
    b = (P @ origins[:, :, None]).sum(0)[:, 0]
    if len(origins) < 2 or np.linalg.eigvalsh(A / len(origins)).min() < 1e-3:
        return np.zeros(3), False
    return np.linalg.solve(A, b), True


def half_fov(K: np.ndarray, wh: tuple[int, int]) -> float:
    """Half field of view along the narrower side: ``min(atan(min(cx, W-cx)/fx), atan(min(cy, H-cy)/fy))``."""
    w, h = wh
    ax = np.arctan(max(min(K[0, 2], w - K[0, 2]), 1e-6) / K[0, 0])
    ay = np.arctan(max(min(K[1, 2], h - K[1, 2]), 1e-6) / K[1, 1])
    return float(min(ax, ay))


def frustum_radius(Ks: np.ndarray, c2w: np.ndarray, wh: tuple[int, int], centre: np.ndarray) -> float:
    """``min_i |o_i - c| sin(phi_i)``: the largest ball around ``c`` every camera sees whole."""
    d = np.linalg.norm(c2w[:, :3, 3] - centre, axis=-1)
    phis = np.array([half_fov(K, wh) for K in Ks])
    return float((d * np.sin(phis)).min())


def projection_matrices(Ks: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """``P_i = K_i [R_i^T | -R_i^T o_i]``: ``[N, 3, 3], [N, 4, 4] -> [N, 3, 4]`` (world -> pixels)."""
    Rt = np.transpose(c2w[:, :3, :3], (0, 2, 1))
    w2c = np.concatenate([Rt, -Rt @ c2w[:, :3, 3:4]], axis=2)
    return Ks @ w2c


def _project(P, pts):
    """World points ``[M, 3]`` -> pixel coords ``u, v`` and depth ``z``, each ``[N, M]``."""
    ph = np.concatenate([pts, np.ones_like(pts[:, :1])], 1).T.astype(np.float32)  # [4, M]
    n = P.shape[0]
    uvw = (P.reshape(n * 3, 4).astype(np.float32) @ ph).reshape(n, 3, -1)  # one GEMM
    # row 2 is the depth since K[2] = (0, 0, 1)
    z = uvw[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return uvw[:, 0] / z, uvw[:, 1] / z, z


def carve(Ks: np.ndarray, c2w: np.ndarray, masks: np.ndarray, pts: np.ndarray,
          views_per_step: int = 8) -> np.ndarray:
    """Visual-hull test of points ``[P, 3]`` -> bool ``[P]``.

    A point survives when it projects (pixel centres at +0.5: pixel ``floor(u), floor(v)``)
    into a foreground pixel of every mask whose image it falls in (in front of the camera),
    and falls in at least half of the images. Views are processed a few at a time and
    rejected points are dropped as we go, so the cost shrinks with the hull.
    """
    n, h, w = masks.shape
    P = projection_matrices(Ks, c2w)
    alive = np.arange(len(pts))
    seen = np.zeros(len(pts), np.int32)
    for s in range(0, n, views_per_step):
        u, v, z = _project(P[s:s + views_per_step], pts[alive])
        u = np.floor(u)
        v = np.floor(v)
        inside = (z > 1e-9) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ui = np.where(inside, u, 0).astype(np.int64)
        vi = np.where(inside, v, 0).astype(np.int64)
        fg = masks[np.arange(s, s + len(u))[:, None], vi, ui]
        ok = (~inside | fg).all(0)
        seen[alive] += inside.sum(0)
        alive = alive[ok]
        if not len(alive):
            break
    keep = np.zeros(len(pts), bool)
    keep[alive] = seen[alive] * 2 >= n
    return keep


def _grid(lo: np.ndarray, hi: np.ndarray, res: int) -> tuple[np.ndarray, float]:
    step = (hi - lo).max() / res
    centre = 0.5 * (lo + hi)
    ax = (np.arange(res) + 0.5 - res / 2) * step
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3) + centre
    return g, float(step)


def visual_hull_ball(Ks: np.ndarray, c2w: np.ndarray, masks: np.ndarray, centre0: np.ndarray,
                     res: int = 64) -> tuple[np.ndarray, float] | None:
    """Bounding ball ``(c [3], r)`` of a two-pass ``res^3`` visual hull, or None if empty."""
    half = 0.95 * np.linalg.norm(c2w[:, :3, 3] - centre0, axis=-1).min()
    lo, hi = centre0 - half, centre0 + half
    for _ in range(2):
        pts, step = _grid(lo, hi, res)
        keep = carve(Ks, c2w, masks, pts)
        if not keep.any():
            return None
        kp = pts[keep]
        lo, hi = kp.min(0) - step, kp.max(0) + step
    c = 0.5 * (kp.min(0) + kp.max(0))
    r = np.linalg.norm(kp - c, axis=-1).max() + 0.5 * np.sqrt(3) * step
    return c, float(r)


def normalization_from_cameras(Ks: np.ndarray, c2w_world: np.ndarray, wh: tuple[int, int],
                               masks: np.ndarray | None = None, *, margin: float = 1.1
                               ) -> Normalization:
    """Estimate ``world_from_norm`` from cameras (and masks) with the rule in the module docstring.

    Args:
        Ks: ``[N, 3, 3]`` intrinsics on the grid of ``masks`` (Scene convention).
        c2w_world: ``[N, 4, 4]`` OpenCV camera-to-world.
        wh: image ``(W, H)`` matching ``Ks``.
        masks: ``[N, H, W]`` bool or None.
        margin: factor applied to the estimated radius.
    """
    o = c2w_world[:, :3, 3]
    d = c2w_world[:, :3, 2]
    c0, ok = nearest_point_to_axes(o, d)

    def capped(c, r, method):
        cam = np.linalg.norm(o - c, axis=-1).min() / CAMERA_CLEARANCE
        if not np.isfinite(r) or r <= 0 or cam <= 0:
            raise DatasetError("cannot place the object: a camera sits at the estimated scene centre",
                               code="singular_camera")
        return Normalization(c, float(min(margin * r, cam)), method)

    if masks is not None and len(Ks) >= 3:
        ball = visual_hull_ball(Ks, c2w_world, masks, c0)
        if ball is not None:
            return capped(ball[0], ball[1], "visual_hull")
    return capped(c0, frustum_radius(Ks, c2w_world, wh, c0), "frustum")
