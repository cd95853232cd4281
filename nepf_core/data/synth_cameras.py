"""The scene maker's cameras: Fibonacci spirals around the object, looking at its centre.

``n_views`` training and ``n_test`` test cameras on spirals at ``camera_distance`` (object units)
from the centre, elevation in :data:`ELEVATION_DEG`, +Z up; the test spiral is rotated by half a
step so test views differ from training views. Each camera is recorded in the world frame
``x_world = s x_obj + o`` in the DTU (``world_mat = K_cv [R|t]``), OpenCV and OpenGL/Blender
conventions (:func:`world_camera`).
"""

from __future__ import annotations

import math

import numpy as np

ELEVATION_DEG = (-25.0, 65.0)


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera-to-world ``[4, 4]``: z forward to ``target``, x = z x up (right), y = z x x (down)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def spiral_positions(n: int, distance: float, phase: float) -> np.ndarray:
    """``[n, 3]`` points at ``distance`` on a Fibonacci spiral within :data:`ELEVATION_DEG`.

    ``z_k = sin(lo) + (k + 0.5)/n (sin(hi) - sin(lo))`` (equal-area), azimuth
    ``phi_k = (k + phase) * golden_angle``.
    """
    lo, hi = (math.radians(a) for a in ELEVATION_DEG)
    k = np.arange(n) + 0.5
    z = math.sin(lo) + k / n * (math.sin(hi) - math.sin(lo))
    phi = (np.arange(n) + phase) * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return distance * np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def intrinsics(w: int, h: int, fov_deg: float) -> np.ndarray:
    """Scene-convention ``K`` (pixel centres at +0.5), ``fov_deg`` across the narrower side:
    ``fx = fy = min(W, H) / (2 tan(fov/2))``, ``c = (W/2, H/2)``."""
    f = 0.5 * min(w, h) / math.tan(math.radians(fov_deg) / 2)
    return np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])


def auto_fov_deg(distance: float) -> float:
    """``2.16 asin(min(0.95, 1 / distance))`` in degrees: the unit ball's angular diameter + 8%."""
    return math.degrees(2.16 * math.asin(min(0.95, 1.0 / distance)))


def spiral_cameras(n_views: int, n_test: int, distance: float, seed: int) -> dict[str, list[np.ndarray]]:
    """``{"train": [c2w], "test": [c2w]}`` in object units: the training spiral's azimuth phase
    is ``frac(0.618... seed)``, the test spiral's half a step further."""
    phase = (seed * 0.61803398875) % 1.0
    pos = {"train": spiral_positions(n_views, distance, phase),
           "test": spiral_positions(n_test, distance, phase + 0.5) if n_test else np.zeros((0, 3))}
    return {k: [look_at(p, np.zeros(3)) for p in v] for k, v in pos.items()}


def world_camera(K: np.ndarray, c2w_obj: np.ndarray, s: float, off: np.ndarray) -> dict:
    """World-frame camera records for one view (DTU, OpenCV, OpenGL)."""
    c2w = c2w_obj.copy()
    c2w[:3, 3] = s * c2w_obj[:3, 3] + off
    w2c = np.linalg.inv(c2w)
    K_cv = K.copy()
    K_cv[0, 2] -= 0.5
    K_cv[1, 2] -= 0.5  # OpenCV: pixel centres at integers
    K4 = np.eye(4)
    K4[:3, :3] = K_cv
    return {"K_opencv": K_cv, "c2w_opencv": c2w, "w2c_opencv": w2c, "world_mat": K4 @ w2c,
            "c2w_opengl_blender": c2w @ np.diag([1.0, -1.0, -1.0, 1.0])}


def camera_record(cams: dict, scale_mat: np.ndarray, K: np.ndarray, w: int, h: int, distance: float) -> dict:
    """``scene.json["cameras"]``: the shared intrinsics and every split's world matrices."""
    def split_json(split):
        return [{"index": i, "width": w, "height": h, **{k: v.tolist() for k, v in c.items()},
                 "scale_mat": scale_mat.tolist(), "camera_angle_x": 2.0 * math.atan(0.5 * w / K[0, 0])}
                for i, c in enumerate(cams[split])]
    return {"distance_to_center": distance, "fov_x_deg": math.degrees(2.0 * math.atan(0.5 * w / K[0, 0])),
            "width": w, "height": h, "train": split_json("train"), "test": split_json("test")}
