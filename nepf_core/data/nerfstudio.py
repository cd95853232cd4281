"""nerfstudio layout: ``transforms.json`` as ``ns-process-data`` writes it.

It is instant-ngp's file (``ingp.py``: ``fl_x, fl_y, cx, cy, w, h``, ``k1, k2, p1, p2``, OpenGL
``transform_matrix``) with keys of its own, told apart by them (:data:`NERFSTUDIO_KEYS`):

* ``camera_model``: PINHOLE, SIMPLE_PINHOLE and OPENCV load (undistorted at load, ``k4`` is the
  ``r^8`` term); OPENCV_FISHEYE and EQUIRECTANGULAR are refused by name (``camera_models.py``).
* per-frame intrinsics (``fl_x`` ... ``k1`` ... in a frame override the top level), as
  ``ns-process-data`` writes them when COLMAP found several cameras. The images must still
  share one size (``Scene`` holds one ``H x W``).
* ``frames[].mask_path``: a mask per frame, read like DTU's (``blender.frame_mask``).
* ``applied_transform`` ``A`` (3x4): ``ns-process-data`` rotates COLMAP's world before writing
  the poses, ``transform_matrix = A c2w_colmap`` (``A`` swaps y and z and negates the new z,
  so that z is up). The normalisation is computed in the file's frame, and the way back to the
  capture's own world is kept in ``world_from_norm``:

      ``world_from_norm = A^-1 world_from_norm_file``

  so exports, metrics and relighting are in COLMAP's world frame, the same frame a COLMAP
  loader of the same capture gives. ``A`` must be a similarity without reflection.
* ``ply_file_path``: the sparse point cloud (``sparse_pc.ply``), written in the file's frame
  (``A`` applied); it becomes ``Scene.points`` (normalised frame) and serves the object region
  in place of the points triangulated from the images (``colmap.py`` says why).

Views: every frame, in the file's order (no splits, as instant-ngp).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nepf_core.data.assemble import check_whole_set
from nepf_core.data.errors import DatasetError
from nepf_core.data.paths import dataset_path, existing_file, rel
from nepf_core.data.scene import Scene

TRANSFORMS = "transforms.json"
#: Any of these in ``transforms.json`` makes it nerfstudio's rather than instant-ngp's.
NERFSTUDIO_KEYS = ("camera_model", "applied_transform", "ply_file_path")


def is_nerfstudio(root: Path) -> bool:
    """True when ``root/transforms.json`` is a JSON object with one of :data:`NERFSTUDIO_KEYS`
    (an unreadable file is left to the instant-ngp loader, which names the error)."""
    from nepf_core.data.blender import read_json   # the one (bounded) JSON reader of transforms files

    path = existing_file(root, TRANSFORMS)
    if path is None:
        return False
    try:
        meta = read_json(path, Path(root))
    except DatasetError:
        return False
    return any(k in meta for k in NERFSTUDIO_KEYS)


def applied_transform(meta: dict, label: str) -> np.ndarray | None:
    """``[4, 4]`` ``A`` from ``applied_transform`` (3x4 or 4x4), or None; ``invalid_camera`` unless
    ``A[:3, :3] = s Q`` with ``Q`` a rotation (``Q^T Q = I`` within 1e-4, ``det > 0``)."""
    if meta.get("applied_transform") is None:
        return None
    try:
        m = np.array(meta["applied_transform"], dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape not in ((3, 4), (4, 4)) or not np.isfinite(m).all():
        raise DatasetError("'applied_transform' must be a 3x4 matrix of finite numbers", file=label,
                           code="bad_json")
    A = np.eye(4)
    A[:3] = m[:3]
    det = np.linalg.det(A[:3, :3])
    s = np.cbrt(det) if det > 0 else 0.0
    if s <= 0 or np.abs(A[:3, :3].T @ A[:3, :3] / (s * s) - np.eye(3)).max() > 1e-4:
        raise DatasetError("'applied_transform' is not a rotation (with translation and uniform scale)",
                           file=label, code="invalid_camera")
    return A


def ply_path(meta: dict, root: Path, label: str) -> Path | None:
    """The ``ply_file_path`` file (relative to the JSON's folder, inside ``root``), or None."""
    written = meta.get("ply_file_path")
    if written is None:
        return None
    if not isinstance(written, str):
        raise DatasetError("'ply_file_path' must be a string", file=label, code="bad_json")
    p = dataset_path(root, written, file=label)
    if not p.is_file():
        raise DatasetError("point cloud file not found", file=rel(p, root), code="missing_file")
    return p


def read_ply_points(path: Path, root: Path) -> np.ndarray:
    """Vertex positions ``[P, 3]`` float64 of a PLY file (ASCII or binary, by trimesh, a
    dependency already); ``unreadable_points`` naming the file when it is not a readable PLY."""
    import trimesh

    try:
        geom = trimesh.load(str(path), file_type="ply", process=False)
        pts = np.asarray(geom.vertices, dtype=np.float64).reshape(-1, 3)
    except Exception as e:  # trimesh raises many types on malformed files
        raise DatasetError(f"cannot read the point cloud: {type(e).__name__}", file=rel(path, root),
                           code="unreadable_points") from None
    return pts[np.isfinite(pts).all(1)]


def nerfstudio_extras(root: Path | str) -> tuple[np.ndarray | None, Path | None]:
    """``(A or None, ply file or None)`` of a nerfstudio folder (the views are parsed by
    :func:`nepf_core.data.blender.parse_transforms`)."""
    from nepf_core.data.blender import read_json

    root = Path(root)
    meta = read_json(root / TRANSFORMS, root)
    return applied_transform(meta, TRANSFORMS), ply_path(meta, root, TRANSFORMS)


def load_nerfstudio(root: Path | str, split: str = "train", *, downscale: int = 1,
                    max_views: int | None = None, max_side: int | None = None,
                    max_total_pixels: int | None = None) -> Scene:
    """Load a nerfstudio ``transforms.json`` folder as a :class:`Scene` (module docstring).

    ``split`` must be ``"train"`` or ``"all"``. ``max_side`` and ``max_total_pixels``: see
    :func:`nepf_core.data.blender.load_transforms`.
    """
    from nepf_core.data.blender import load_transforms
    from nepf_core.data.colmap import points_in_frame

    root = Path(root)
    check_whole_set(split, "nerfstudio", "all frames", TRANSFORMS)
    A, ply = nerfstudio_extras(root)
    scene = load_transforms(root, root / TRANSFORMS, fmt="nerfstudio", split=split, downscale=downscale,
                            max_views=max_views, max_side=max_side, max_total_pixels=max_total_pixels)
    if ply is not None:
        scene.points = points_in_frame(read_ply_points(ply, root), scene.world_from_norm)
        scene.extras["sparse_points"] = 0 if scene.points is None else int(len(scene.points))
    if A is not None:
        scene.world_from_norm = np.linalg.inv(A) @ scene.world_from_norm
        scene.extras["applied_transform"] = A[:3].tolist()
    return scene
