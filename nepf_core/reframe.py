"""Express a scene's cameras in another run's normalised frame.

Two datasets of the same object (train and held-out views) may have been normalised
differently. With ``S = world_from_norm`` of the scene and ``T`` the target's,

    c2w' = (T^{-1} S) c2w,   then the 3x3 block is divided by the uniform scale k of T^{-1} S

so camera centres land where they belong and rotations stay orthonormal.
"""

from __future__ import annotations

import numpy as np

from nepf_core.data.scene import Scene


def reframe_scene(scene: Scene, target_world_from_norm: np.ndarray) -> Scene:
    """A copy of ``scene`` whose ``c2w`` and ``world_from_norm`` use the target frame."""
    T = np.asarray(target_world_from_norm, dtype=np.float64)
    S = np.asarray(scene.world_from_norm, dtype=np.float64)
    M = np.linalg.inv(T) @ S
    k = float(np.cbrt(abs(np.linalg.det(M[:3, :3]))))
    c2w = np.einsum("ij,njk->nik", M, scene.c2w.astype(np.float64))
    c2w[:, :3, :3] /= k
    out = scene.subset(np.arange(scene.n_views))
    out.c2w = c2w.astype(np.float32)
    out.world_from_norm = T.copy()
    if scene.points is not None:
        p = np.asarray(scene.points, dtype=np.float64)
        out.points = (p @ M[:3, :3].T + M[:3, 3]).astype(np.float32)
    return out


def object_world_from_norm(world_from_norm: np.ndarray, centre, radius: float) -> np.ndarray:
    """The frame whose unit sphere is the ball ``(centre [3], radius)`` of the frame
    ``world_from_norm``: ``world_from_norm @ [[radius I, centre], [0, 1]]`` (``[4, 4]``)."""
    M = np.eye(4)
    M[:3, :3] *= float(radius)
    M[:3, 3] = np.asarray(centre, dtype=np.float64)
    return np.asarray(world_from_norm, dtype=np.float64) @ M


def load_held_out(root, target_world_from_norm: np.ndarray, *, downscale: int = 1,
                  max_side: int | None = None, max_total_pixels: int | None = None) -> Scene:
    """Load a held-out dataset folder (its ``test`` split for Blender layouts, every view
    otherwise) at the working resolution ``max_side`` (0/None: full size), refusing more than
    ``max_total_pixels`` decoded pixels (None/0: no cap), and express it in the target run's
    normalised frame."""
    from pathlib import Path

    from nepf_core.data.detect import load_scene, resolve_dataset
    fmt, folder = resolve_dataset(root)
    split = "test" if fmt == "blender" and (Path(folder) / "transforms_test.json").exists() else (
        "train" if fmt == "blender" else "all")
    return reframe_scene(load_scene(folder, split=split, downscale=downscale, max_side=max_side,
                                    max_total_pixels=max_total_pixels), target_world_from_norm)
