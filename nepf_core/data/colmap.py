"""COLMAP layout: ``sparse/0/`` (or ``sparse/``) with a sparse model, beside ``images/``.

What ``colmap automatic_reconstructor --workspace_path D --image_path D/images`` writes is
``D/sparse/0/{cameras,images,points3D}.bin``; ``colmap image_undistorter`` writes ``sparse/``
(no ``0``) beside ``images/``; ``colmap model_converter --output_type TXT`` gives the ``.txt``
form. All three load. Model files are read by :mod:`nepf_core.data.colmap_io`.

Views: every registered image, sorted by name (COLMAP's ids follow the order of matching, not
of capture); ``images.txt``'s ``NAME`` is relative to ``images/`` and must resolve inside the
dataset (``paths.py``). Unregistered photos in ``images/`` are not views.

Cameras: ``c2w = [[R^T, -R^T t], [0, 1]]`` from the world-to-camera ``(R(q), t)``; the axes are
OpenCV's already. Intrinsics and distortion per camera model (:mod:`nepf_core.data.camera_models`:
SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; the images are undistorted at load as
instant-ngp's are, ``ingp.py``); every other model is refused by name. The camera's declared
``width x height`` must be the image file's (a resized ``images/`` would silently scale K).
COLMAP's pixel centres sit at +0.5, ``Scene``'s convention, so ``K`` is used as written.

Normalisation: as instant-ngp's (COLMAP has no masks; an RGBA image set gives alpha masks as in
``blender.py``): the camera rule of ``normalize.py`` on the cameras, shared by every view.

Sparse points: ``points3D`` (world) are mapped into the normalised frame and kept in
``Scene.points``; without masks they are where the object region is looked for
(``nepf_core/train/rules/masks.py``) in place of the ORB points triangulated from the images:
COLMAP's points come from its own matching and bundle adjustment over every image, so they are
denser and better placed than a few neighbour pairs' ORB matches, and they cost nothing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nepf_core.data.assemble import check_whole_set, read_normalized_views, scene_from_views
from nepf_core.data.camera_models import colmap_intrinsics
from nepf_core.data.colmap_io import ColmapModel, model_ext, qvec_to_rotmat, read_model
from nepf_core.data.errors import DatasetError
from nepf_core.data.images import is_image_name
from nepf_core.data.normalize import check_c2w
from nepf_core.data.paths import dataset_path, existing_dir, rel
from nepf_core.data.scene import Scene
from nepf_core.data.views import ViewSpec

#: Where the sparse model may be, in order.
MODEL_DIRS = ("sparse/0", "sparse")
IMAGE_DIR = "images"


def find_model_dir(root: Path) -> Path | None:
    """The first of :data:`MODEL_DIRS` under ``root`` holding a model (inside ``root``), or None."""
    for name in MODEL_DIRS:
        d = existing_dir(root, name)
        if d is not None and model_ext(d) is not None:
            return d
    return None


def is_colmap(root: Path) -> bool:
    """True when ``root`` has a sparse model (:data:`MODEL_DIRS`) and an ``images/`` folder."""
    root = Path(root)
    return existing_dir(root, IMAGE_DIR) is not None and find_model_dir(root) is not None


def world_to_camera(qvec, tvec) -> np.ndarray:
    """``[4, 4]`` world-to-camera ``[[R(q), t], [0, 1]]`` (``colmap_io`` gives ``R(q)``)."""
    m = np.eye(4)
    m[:3, :3] = qvec_to_rotmat(qvec)
    m[:3, 3] = tvec
    return m


def specs_from_model(model: ColmapModel, root: Path, model_label: str) -> list[ViewSpec]:
    """One :class:`ViewSpec` per registered image, sorted by name (module docstring)."""
    images = sorted(model.images.values(), key=lambda im: im.name)
    if not images:
        raise DatasetError("the COLMAP model has no registered image", file=model_label, code="no_views")
    label = f"{model_label}/images{model.ext}"
    specs = []
    for i, im in enumerate(images):
        cam = model.cameras.get(im.camera_id)
        if cam is None:
            raise DatasetError(f"image {im.name} uses camera {im.camera_id}, which is not in "
                               f"cameras{model.ext}", file=label, view=i, code="invalid_camera")
        K, dist = colmap_intrinsics(cam.model, cam.params, label=f"{model_label}/cameras{model.ext}", view=i)
        if not (np.isfinite(im.qvec).all() and np.isfinite(im.tvec).all()) or np.linalg.norm(im.qvec) < 1e-12:
            raise DatasetError(f"image {im.name} has a non-finite or zero pose", file=label, view=i,
                               code="nonfinite_camera")
        c2w = check_c2w(np.linalg.inv(world_to_camera(im.qvec, im.tvec)), label=label, view=i)
        path = dataset_path(root, im.name, base=root / IMAGE_DIR, file=label, view=i)
        if not path.is_file():
            raise DatasetError(f"image {im.name} of the COLMAP model is not in {IMAGE_DIR}/",
                               file=rel(path, root), view=i, code="missing_image")
        if not is_image_name(path.name):
            raise DatasetError(f"unsupported image format '{path.suffix}' (use PNG or JPEG)",
                               file=rel(path, root), view=i, code="unsupported_image")
        specs.append(ViewSpec(image=path, label=rel(path, root), K=K, c2w=c2w,
                              expected_wh=(cam.width, cam.height), distortion=dist))
    return specs


def parse_colmap(root: Path | str) -> tuple[list[ViewSpec], ColmapModel, str]:
    """``(specs, model, model folder label)`` of a COLMAP folder (no pixels read)."""
    root = Path(root)
    folder = find_model_dir(root)
    if folder is None or existing_dir(root, IMAGE_DIR) is None:
        raise DatasetError(f"no {' or '.join(MODEL_DIRS)} model with an {IMAGE_DIR}/ folder", file=".",
                           code="unknown_layout")
    label = rel(folder, root)
    model = read_model(folder, root)
    return specs_from_model(model, root, label), model, label


def points_in_frame(points: np.ndarray | None, world_from_norm: np.ndarray) -> np.ndarray | None:
    """World points ``[P, 3]`` -> the normalised frame ``x_norm = world_from_norm^-1 x_world`` (float32)."""
    if points is None or len(points) == 0:
        return None
    A = np.linalg.inv(np.asarray(world_from_norm, np.float64))
    p = np.asarray(points, np.float64)
    p = p[np.isfinite(p).all(1)]
    return (p @ A[:3, :3].T + A[:3, 3]).astype(np.float32)


def load_colmap(root: Path | str, split: str = "train", *, downscale: int = 1,
                max_views: int | None = None, max_side: int | None = None,
                max_total_pixels: int | None = None) -> Scene:
    """Load a COLMAP folder (module docstring) as a :class:`Scene` of every registered image.

    COLMAP folders have no splits: ``split`` must be ``"train"`` or ``"all"``. ``max_side``
    (working resolution) and ``max_total_pixels`` (decoded-pixel budget): see
    :func:`nepf_core.data.blender.load_transforms`.
    """
    from nepf_core.data.blender import normalization_for_specs

    root = Path(root)
    check_whole_set(split, "COLMAP", "all registered images", ".")
    specs, model, label = parse_colmap(root)
    views, c2w, norm = read_normalized_views(specs, lambda: normalization_for_specs(specs), max_views=max_views,
                                             max_total_pixels=max_total_pixels, downscale=downscale, max_side=max_side)
    points = points_in_frame(model.points, norm.world_from_norm)
    extras = {"normalization": norm.method, "colmap_model": label + "/", "model_format": model.ext[1:],
              "undistorted": any(s.distortion is not None for s in views.specs),
              "camera_models": sorted({model.cameras[im.camera_id].model for im in model.images.values()}),
              "sparse_points": 0 if points is None else int(len(points))}
    return scene_from_views(views, c2w, norm.world_from_norm, root=root, source_format="colmap", split=split,
                            extras=extras, points=points)
