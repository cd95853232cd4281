"""DTU / IDR / NeuS layout: ``cameras(_sphere).npz`` + ``image/`` (+ ``mask/``).

Layout (IDR, NeuS):
    ``cameras_sphere.npz`` (preferred) or ``cameras.npz`` with, per view ``i``:
        * ``world_mat_i`` ``[4, 4]`` or ``[3, 4]``: ``K [R | t]``, world -> pixels (OpenCV,
          pixel centres at integer coordinates);
        * ``scale_mat_i`` ``[4, 4]`` (optional): normalised unit sphere -> world.
    Only these members are read, one at a time, each ``.npy`` header (real dtype, one of these
    shapes, a bounded size) checked before its data (``npz.py``): other members are never
    decompressed.
    ``image/`` (or ``images/``): PNG/JPEG sorted by name; the i-th file is view ``i``.
    ``mask/`` (or ``masks/``, optional): same count, any mode; converted to luma and
    thresholded at 127, so 3-channel soft-edged DTU masks work.
    The camera file, the folders and every file in them must resolve inside the dataset
    folder (``paths.py``): a symbolic link out of it is ``path_outside_dataset``.

Cameras: ``P = world_mat_i @ scale_mat_i`` maps normalised points to pixels, and is
decomposed into ``K`` and ``c2w`` (normalised frame) by :func:`decompose_projection`;
``world_from_norm = scale_mat``. OpenCV's pixel centres sit at integer coordinates while
``Scene`` puts them at +0.5, so ``K[0, 2]`` and ``K[1, 2]`` gain 0.5.

Without ``scale_mat`` the normalisation is estimated from the cameras (visual hull of the
masks when present) by :func:`nepf_core.data.normalize.normalization_from_cameras`,
and ``Scene.extras["normalization"]`` says which rule was used.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import scipy.linalg

from nepf_core.data.assemble import check_whole_set, read_views, scene_from_views
from nepf_core.data.budget import check_total_pixels
from nepf_core.data.errors import DatasetError
from nepf_core.data.images import list_images
from nepf_core.data.normalize import (as_4x4, c2w_to_normalized, check_intrinsics,
                                      normalization_from_cameras)
from nepf_core.data.npz import NpzArrays
from nepf_core.data.paths import existing_dir, existing_file, rel
from nepf_core.data.scene import Scene
from nepf_core.data.views import ViewSpec

CAMERA_FILES = ("cameras_sphere.npz", "cameras.npz")
IMAGE_DIRS = ("image", "images")
MASK_DIRS = ("mask", "masks")


def find_camera_file(root: Path) -> Path | None:
    """The first of :data:`CAMERA_FILES` present in ``root`` (inside it), or None."""
    for name in CAMERA_FILES:
        if (p := existing_file(root, name)) is not None:
            return p
    return None


def find_dir(root: Path, names: tuple[str, ...]) -> Path | None:
    """The first existing sub-folder of ``root`` among ``names`` (inside it), or None."""
    for name in names:
        if (p := existing_dir(root, name)) is not None:
            return p
    return None


def is_dtu(root: Path) -> bool:
    """True when ``root`` has a camera npz and an image folder."""
    root = Path(root)
    return find_camera_file(root) is not None and find_dir(root, IMAGE_DIRS) is not None


def decompose_projection(P: np.ndarray, *, label: str | None = None, view: int | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Split a ``[3, 4]`` projection ``P ~ K [R | t]`` into ``K [3, 3]`` and ``c2w [4, 4]``.

    Steps: flip the sign of ``P`` if ``det P[:, :3] < 0`` (same projective camera, points in
    front get positive depth); RQ-decompose ``M = P[:, :3] = K R``; make ``diag K`` positive
    with ``D = diag(sign(diag K))`` (``K <- K D``, ``R <- D R``); scale ``K[2, 2] = 1``.
    The camera centre is ``C = -M^{-1} p_4`` and ``c2w = [[R^T, C], [0, 1]]``.
    ``K`` is returned in the OpenCV convention (pixel centres at integers).

    Raises ``nonfinite_camera`` or ``singular_camera`` (``sigma_min / sigma_max < 1e-12``).
    """
    P = np.asarray(P, dtype=np.float64)
    if not np.isfinite(P).all():
        raise DatasetError("projection matrix has NaN or infinite entries", file=label, view=view,
                           code="nonfinite_camera")
    M = P[:, :3]
    sv = np.linalg.svd(M, compute_uv=False)
    if sv[0] == 0 or sv[-1] / sv[0] < 1e-12:
        raise DatasetError("projection matrix is singular (rank < 3)", file=label, view=view,
                           code="singular_camera")
    if np.linalg.det(M) < 0:
        P = -P
        M = -M
    K, R = scipy.linalg.rq(M)
    D = np.diag(np.sign(np.diag(K)))
    K = K @ D
    R = D @ R
    K = K / K[2, 2]
    C = -np.linalg.solve(M, P[:, 3])
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = C
    return K, c2w


#: the shapes a DTU camera member may declare (checked from its .npy header, before its data)
MATRIX_SHAPES = {"world_mat": ((4, 4), (3, 4)), "scale_mat": ((4, 4),)}


def open_camera_npz(path: Path, root: Path) -> NpzArrays:
    """The camera file, opened for member-by-member reading (``nepf_core/data/npz.py``): a file
    that is not a zip of ``.npy`` arrays is ``unreadable_cameras`` ("not a valid .npz"), never
    read as a pickle; only the ``world_mat_i`` / ``scale_mat_i`` members are ever read."""
    return NpzArrays(path, rel(path, root))


def read_matrix(cams: NpzArrays, key: str, view: int) -> np.ndarray:
    """Member ``key`` (``world_mat_i`` or ``scale_mat_i``) as a float64 ``[4, 4]``: its header
    checked first (real dtype, ``[4, 4]`` or ``[3, 4]``), then its entries (finite)."""
    kind = key.rsplit("_", 1)[0]
    return as_4x4(cams.read(key, MATRIX_SHAPES[kind], view=view), key, label=cams.label, view=view)


def _shared_scale(cams: NpzArrays, idx: list[int]) -> np.ndarray | None:
    """``scale_mat_0`` when every view has one and they all agree; None when none has one."""
    has_scale = [f"scale_mat_{i}" in cams for i in idx]
    if any(has_scale) and not all(has_scale):
        v = has_scale.index(False)
        raise DatasetError(f"scale_mat_{v} is missing while other views have one", file=cams.label,
                           view=v, code="count_mismatch")
    if not all(has_scale) or not idx:
        return None
    scale = read_matrix(cams, "scale_mat_0", 0)
    for i in idx:
        si = read_matrix(cams, f"scale_mat_{i}", i)
        if not np.allclose(si, scale, rtol=1e-6, atol=1e-9 * max(1.0, np.abs(scale).max())):
            raise DatasetError(f"scale_mat_{i} differs from scale_mat_0; the views would not share "
                               "one normalised frame", file=cams.label, view=i, code="invalid_camera")
    if abs(np.linalg.det(scale[:3, :3])) < 1e-12:
        raise DatasetError("scale_mat is singular", file=cams.label, view=0, code="singular_camera")
    return scale


def _view_files(root: Path, img_dir: Path, idx: list[int], cam_label: str) -> tuple[list, list | None]:
    """``(images, masks or None)``, checked against the camera indices ``idx``."""
    images = list_images(img_dir, root)
    if not images:
        raise DatasetError("the image folder holds no PNG/JPEG image", file=rel(img_dir, root),
                           code="no_views")
    if idx != list(range(len(idx))):
        missing = sorted(set(range(max(idx, default=-1) + 1)) - set(idx))
        raise DatasetError(f"world_mat keys are not numbered 0..N-1 (missing {missing[:5]})",
                           file=cam_label, view=missing[0] if missing else None, code="count_mismatch")
    if len(idx) != len(images):
        raise DatasetError(f"{len(images)} images in {rel(img_dir, root)}/ but {len(idx)} cameras "
                           f"(world_mat_i) in {cam_label}", file=cam_label,
                           view=min(len(idx), len(images)), code="count_mismatch")
    mask_dir = find_dir(root, MASK_DIRS)
    if mask_dir is None:
        return images, None
    masks = list_images(mask_dir, root)
    if len(masks) != len(images):
        raise DatasetError(f"{len(masks)} masks in {rel(mask_dir, root)}/ but {len(images)} images",
                           file=rel(mask_dir, root), view=min(len(masks), len(images)), code="count_mismatch")
    return images, masks


def parse_dtu(root: Path | str) -> tuple[list[ViewSpec], np.ndarray | None, dict]:
    """Read the cameras and file lists (no pixels).

    Returns ``(specs, world_from_norm or None, info)``: ``specs[i].c2w`` is in the normalised
    frame when ``scale_mat`` exists (``world_from_norm = scale_mat_0``), else in world.
    Raises ``DatasetError`` for missing files, count mismatches and bad matrices. Only the
    ``world_mat_i`` / ``scale_mat_i`` members of the camera file are read, each header first
    (``npz.py``).
    """
    root = Path(root)
    cam_path = find_camera_file(root)
    if cam_path is None:
        raise DatasetError(f"no {' or '.join(CAMERA_FILES)} in the DTU folder", file=".",
                           code="unknown_layout")
    img_dir = find_dir(root, IMAGE_DIRS)
    if img_dir is None:
        raise DatasetError("no image/ folder next to the camera file", file=".", code="unknown_layout")
    with open_camera_npz(cam_path, root) as cams:
        idx = sorted(int(m.group(1)) for k in cams.names if (m := re.fullmatch(r"world_mat_(\d+)", k)))
        images, masks = _view_files(root, img_dir, idx, cams.label)
        scale = _shared_scale(cams, idx)
        specs = []
        for i in idx:
            W = read_matrix(cams, f"world_mat_{i}", i)
            P = (W @ scale if scale is not None else W)[:3, :4]
            K, c2w = decompose_projection(P, label=cams.label, view=i)
            K = K.copy()
            K[0, 2] += 0.5
            K[1, 2] += 0.5
            check_intrinsics(K, label=cams.label, view=i)
            specs.append(ViewSpec(
                image=images[i], label=rel(images[i], root), K=K, c2w=c2w,
                mask=None if masks is None else masks[i],
                mask_label=None if masks is None else rel(masks[i], root)))
    info = {"camera_file": cams.label, "has_scale_mat": scale is not None}
    return specs, scale, info


def load_dtu(root: Path | str, split: str = "train", *, downscale: int = 1,
             max_views: int | None = None, max_side: int | None = None,
             max_total_pixels: int | None = None) -> Scene:
    """Load a DTU/IDR/NeuS folder as a :class:`Scene` (see module docstring).

    DTU folders have no splits: ``split`` must be ``"train"`` or ``"all"`` and every view
    is returned. ``max_views`` keeps evenly spaced views (:func:`~nepf_core.data.assemble.pick_views`); ``max_side``
    is the working resolution (0/None: full size, ``views.py``) and ``max_total_pixels`` the
    decoded-pixel budget, checked from the image headers before decoding (``budget.py``).
    """
    root = Path(root)
    check_whole_set(split, "DTU", "all views", ".")
    specs, scale, info = parse_dtu(root)
    check_total_pixels([s.image for s in specs], max_total_pixels)
    views = read_views(specs, max_views=max_views, downscale=downscale, max_side=max_side)
    c2w = views.c2w()
    if scale is not None:
        wfn = scale
        info["normalization"] = "scale_mat"
    else:
        norm = normalization_from_cameras(views.Ks, c2w, (views.images.shape[2], views.images.shape[1]), views.masks)
        wfn = norm.world_from_norm
        c2w = c2w_to_normalized(c2w, wfn)
        info["normalization"] = norm.method
    return scene_from_views(views, c2w, wfn.astype(np.float64), root=root, source_format="dtu", split=split,
                            extras=info)
